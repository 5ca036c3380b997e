"""Meca500 + instrument kinematics in Drake, at the millimetre/radian interface."""
from __future__ import annotations

import numpy as np
import pytest

from planning.ik import IKFailure, rcm_ik
from planning.robot import Robot


@pytest.fixture(scope="module")
def robot():
    return Robot()


def test_flange_at_zero_is_where_the_datasheet_says(robot):
    R, p = robot.pose("F", np.zeros(6))
    np.testing.assert_allclose(p, [190.0, 0.0, 308.0], atol=1e-9)
    np.testing.assert_allclose(R[:, 0], [1.0, 0.0, 0.0], atol=1e-12)  # flange normal +x
    np.testing.assert_allclose(robot.point("T", np.zeros(3), np.zeros(6)), [282.0, 0.0, 308.0], atol=1e-9)
    np.testing.assert_allclose(robot.pose("S", np.zeros(6))[0][:, 2], [1.0, 0.0, 0.0], atol=1e-7)  # beam along the shaft


def test_limits_are_the_datasheet_limits(robot):
    np.testing.assert_allclose(np.degrees(robot.q_lower), [-175, -70, -135, -170, -115, -180], atol=1e-5)
    np.testing.assert_allclose(np.degrees(robot.q_upper), [175, 90, 70, 170, 115, 180], atol=1e-5)
    np.testing.assert_allclose(np.degrees(robot.qdot_max), [150, 150, 180, 300, 300, 500], atol=1e-5)


def test_jacobians_match_finite_differences(robot):
    q = np.array([0.1, 0.3, -0.4, 0.5, 0.6, -0.2])
    for frame, p in (("T", np.zeros(3)), ("P", np.zeros(3)), ("I", [70.0, 0.0, 0.0])):
        J = robot.jacobian(frame, p, q)
        h = 1e-6
        fd = np.column_stack([(robot.point(frame, p, q + h * e) - robot.point(frame, p, q - h * e)) / (2 * h) for e in np.eye(6)])
        np.testing.assert_allclose(J, fd, atol=1e-5)


def test_rcm_rows_drive_the_lateral_error_down(robot):
    q = np.array([0.0, 0.4, -0.1, 0.0, 0.5, 0.0])
    p_WC = robot.point("I", [75.0, 0.4, -0.3], q)  # 0.5 mm off the shaft
    e0 = robot.rcm_error_mm(q, p_WC)
    for _ in range(200):  # 0.2 s at 1 kHz of pure RCM correction (min-norm velocities)
        A, b = robot.rcm_rows(q, p_WC, gain_per_s=50.0)
        q = q + 1e-3 * np.linalg.lstsq(A, b, rcond=None)[0]
    assert e0 == pytest.approx(0.5, rel=1e-6)
    assert robot.rcm_error_mm(q, p_WC) < 0.5 * np.exp(-50.0 * 0.2) * 1.5  # exponential decay at the gain


def test_ik_through_the_trocar(robot):
    p_WE = np.array([300.0, 0.0, 150.0])
    p_WC = p_WE + [-8.0, 0.0, 7.2]
    q = rcm_ik(robot, p_WE + [0.0, 0.0, -2.0], p_WC, np.array([0, 0.5, 0.3, 0, 0.5, 0]))
    assert robot.rcm_error_mm(q, p_WC) < 1e-3  # target: <= 1 um with IK
    np.testing.assert_allclose(robot.point("T", np.zeros(3), q), p_WE + [0.0, 0.0, -2.0], atol=1e-4)
    assert np.all(robot.joint_margin_rad(q) > 0)


def test_unreachable_and_bad_input_are_refused(robot):
    with pytest.raises(IKFailure, match="tip target"):
        rcm_ik(robot, [900.0, 0.0, 0.0], [880.0, 0.0, 0.0], np.zeros(6))
    with pytest.raises(ValueError, match="q"):
        robot.pose("T", [0.0, np.nan, 0, 0, 0, 0])
    with pytest.raises(ValueError, match="p_WT_mm"):
        rcm_ik(robot, [np.nan, 0, 0], [0, 0, 0], np.zeros(6))
