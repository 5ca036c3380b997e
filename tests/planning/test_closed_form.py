"""Closed-form shaft IK against Drake's forward kinematics."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planning.closed_form import shaft_ik
from planning.robot import Robot

ROBOT = Robot()


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-0.95, 0.95), min_size=6, max_size=6))
def test_every_branch_reproduces_the_tip_and_shaft_and_one_is_the_original(fractions):
    q = ROBOT.q_lower + (np.array(fractions) + 1.0) / 2.0 * (ROBOT.q_upper - ROBOT.q_lower)
    R, p = ROBOT.pose("T", q)
    sols = shaft_ik(p, R[:, 0], ROBOT.tip_offset_mm, q[5])
    assert len(sols) == 8
    for s in sols:
        R_s, p_s = ROBOT.pose("T", s)
        np.testing.assert_allclose(p_s, p, atol=1e-8)  # mm
        np.testing.assert_allclose(R_s[:, 0], R[:, 0], atol=1e-10)
    if abs(np.sin(q[4])) > 1e-3:  # at the wrist singularity J5 = 0, J4 is arbitrary
        wrapped = np.abs((sols - q + np.pi) % (2 * np.pi) - np.pi).max(axis=1)
        assert wrapped.min() < 1e-7


def test_out_of_reach_gives_no_solution():
    assert shaft_ik([600.0, 0.0, 135.0], [1.0, 0.0, 0.0], ROBOT.tip_offset_mm).shape == (0, 6)
    assert ROBOT.tip_offset_mm == pytest.approx(92.0)
