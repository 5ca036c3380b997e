"""Closed-form shaft IK against Drake's forward kinematics; its lengths read off the plant."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planning.closed_form import arm_lengths, shaft_ik
from planning.robot import Robot

ROBOT = Robot()


@settings(max_examples=60)
@given(st.lists(st.floats(-0.95, 0.95), min_size=6, max_size=6))
def test_every_branch_reproduces_the_tip_and_shaft_and_one_is_the_original(fractions):
    q = ROBOT.q_lower + (np.array(fractions) + 1.0) / 2.0 * (ROBOT.q_upper - ROBOT.q_lower)
    R, p = ROBOT.pose("T", q)
    sols = shaft_ik(ROBOT.arm, p, R[:, 0], q[5])
    assert len(sols) == 8
    for s in sols:
        R_s, p_s = ROBOT.pose("T", s)
        np.testing.assert_allclose(p_s, p, atol=1e-8)  # mm
        np.testing.assert_allclose(R_s[:, 0], R[:, 0], atol=1e-10)
    if abs(np.sin(q[4])) > 1e-3:  # at the wrist singularity J5 = 0, J4 is arbitrary
        wrapped = np.abs((sols - q + np.pi) % (2 * np.pi) - np.pi).max(axis=1)
        assert wrapped.min() < 1e-7


def test_out_of_reach_gives_no_solution():
    assert shaft_ik(ROBOT.arm, [600.0, 0.0, 135.0], [1.0, 0.0, 0.0]).shape == (0, 6)
    assert ROBOT.tip_offset_mm == pytest.approx(92.0)


def test_the_lengths_are_the_plants_and_another_layout_is_refused():
    """The Meca500's lengths from meca500.urdf's joints (135 mm shoulder and upper arm, the
    forearm 38 mm up and 120 mm along, W5 -> flange 70 mm); a chain whose J4 axis is
    turned (a wrist that is not spherical) has no closed form here."""
    arm = ROBOT.arm
    np.testing.assert_allclose([arm.shoulder_z_mm, arm.upper_arm_mm, arm.wrist_to_flange_mm], [135.0, 135.0, 70.0],
                               atol=1e-9)
    np.testing.assert_allclose([arm.forearm_mm * np.cos(arm.forearm_angle_rad),
                                arm.forearm_mm * np.sin(arm.forearm_angle_rad)], [120.0, 38.0], atol=1e-9)
    chain = ROBOT.chain
    S = chain.S.copy()
    S[:3, 3] = [0.0, 1.0, 0.0]
    with pytest.raises(ValueError, match="joint layout"):
        arm_lengths(SimpleNamespace(n=6, S=S, p_WJ=chain.p_WJ, homes=chain.homes))
