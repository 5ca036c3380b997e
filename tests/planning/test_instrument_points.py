"""Monitored points from one pose + one spatial Jacobian agree with Drake's per-point queries."""
from __future__ import annotations

import numpy as np
import pytest

from planning.instrument_points import MonitoredPointsConfig, instrument_points


def test_points_jacobians_and_the_trocar_point_match_drake(setup):
    scenario, robot, q0 = setup
    rng = np.random.default_rng(0)
    for q in q0 + 0.02 * rng.standard_normal((5, 6)):
        ip = instrument_points(robot, q, scenario.p_WC)
        np.testing.assert_allclose(ip.P_W[0], robot.pose("T", q)[1], atol=1e-9)
        np.testing.assert_allclose(ip.J_tip, robot.jacobian("T", np.zeros(3), q), atol=1e-9)
        np.testing.assert_allclose(ip.P_W[1], robot.pose("P", q)[1], atol=1e-9)  # the port: the plant's frame P
        np.testing.assert_allclose(ip.J_W[1], robot.jacobian("P", np.zeros(3), q), atol=1e-9)
        for name, p, J in zip(ip.names[2:], ip.P_W[2:], ip.J_W[2:]):
            x = robot.pose("I", q)[0].T @ (p - robot.pose("I", q)[1])
            np.testing.assert_allclose(J, robot.jacobian("I", x, q), atol=1e-9)
        R, p = robot.pose("I", q)
        np.testing.assert_allclose(ip.R_WI, R, atol=1e-12)
        np.testing.assert_allclose(ip.p_WI, p, atol=1e-9)
        lam = R[:, 0] @ (scenario.p_WC - p)  # the trocar's coordinate along the shaft
        np.testing.assert_allclose(ip.J_C, robot.jacobian("I", np.array([lam, 0.0, 0.0]), q), atol=1e-9)
        assert ip.rcm_error_mm == pytest.approx(robot.rcm_error_mm(q, scenario.p_WC), abs=1e-12)


def test_shaft_points_stay_inside_the_eye_and_lens_points_start_at_the_trocar(setup):
    scenario, robot, q = setup
    cfg = MonitoredPointsConfig()
    ip = instrument_points(robot, q, scenario.p_WC, cfg)
    lam = np.linalg.norm(ip.P_W[0] - scenario.p_WC)  # tip's distance past the trocar
    expected = sum(1 for k in range(1, cfg.n_shaft + 1) if lam - k * cfg.shaft_spacing_mm >= cfg.min_depth_past_trocar_mm)
    assert len(ip.names) == 2 + expected
    assert (scenario.eye.signed_distance(ip.P_W) > 0).all()
    d = np.linalg.norm(ip.L_W - scenario.p_WC, axis=1)
    np.testing.assert_allclose(d, [o for o in cfg.lens_offsets_mm if o <= lam], atol=1e-6)
    with pytest.raises(ValueError, match="n_shaft"):
        MonitoredPointsConfig(n_shaft=-1)


def test_the_loops_pose_kernel_is_the_robots_instrument_pose_bit_for_bit(setup):
    """The loop's step reads the end pose of the actuator's pending motion from step_pose;
    the API and replay from Robot.pose("I", q): the same numbers, or a log would not replay."""
    from planning.step_kinematics import step_kinematics_params, step_pose

    scenario, robot, q0 = setup
    kp = step_kinematics_params(robot, scenario.p_WC, MonitoredPointsConfig())
    for q in q0 + 0.3 * np.random.default_rng(1).standard_normal((5, 6)):
        R, p = step_pose(kp, q)
        R_ref, p_ref = robot.pose("I", q)
        np.testing.assert_array_equal(R, R_ref)
        np.testing.assert_array_equal(p, p_ref)
