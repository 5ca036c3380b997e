"""Each constraint's rows from geometry whose answer is known, and the assembly's checks."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from numba import njit

from safety import ConstraintStack, FilterConfig
from safety.constraints import JointPositionLimits, JointSpeedLimits, KeepOut, PointBarrier, RcmEquality, TipSpeedLimit
from safety.constraints.point_barrier import NON_FINITE_FIELD, fill_point_barrier
from safety.constraints.rcm import BRAKING_FACTOR, CANNOT_HOLD, GROWTH_TOL_MM, fill_rcm
from safety.constraints.tip_speed import FACE_NORMALS, REACH, fill_tip_speed


def buffers(rows: int, n: int):
    return np.zeros((rows, n)), np.zeros(rows), np.zeros(rows, dtype=np.int64)


def test_the_tip_speed_polytope_holds_the_ball_and_stays_within_the_limit():
    G, h, ids = buffers(26, 3)
    assert fill_tip_speed(TipSpeedLimit(20.0).params(), np.eye(3), G, h, ids, 0, 7) == 26
    np.testing.assert_allclose(G, FACE_NORMALS)
    np.testing.assert_allclose(h, 20.0 / REACH)
    np.testing.assert_array_equal(ids, 7 + np.arange(26))
    # every unit direction at the face distance is inside; the largest vertex reach stays <= the limit
    rng = np.random.default_rng(0)
    u = rng.standard_normal((2000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    assert np.all(G @ (u * 20.0 / REACH).T <= h[:, None] + 1e-9)
    s = np.max(np.linalg.norm(u, axis=1) / np.max(G @ u.T / h[:, None], axis=0))  # reach of the polytope along u
    assert 0.87 * 20.0 <= s * 1.0 <= 20.0


def test_a_point_barrier_row_is_the_barrier_condition():
    # a point 1.0 mm inside a field whose gradient is +z, Jacobian identity: the row allows an
    # outward speed of gain (h - d_safe - k u) along -z
    b = PointBarrier("g", "f", d_safe_mm=0.5, gain_per_s=20.0, max_recovery_mm_s=5.0, sigma_factor=2.0,
                     calibration_mm=0.05)
    G, h, ids = buffers(1, 3)
    point_h, point_bound = np.full(1, np.nan), np.full(1, np.nan)
    m = fill_point_barrier(b.params(), np.zeros((1, 3)), np.eye(3)[None], 0, 1, np.array([1.0]),
                           np.array([[0.0, 0.0, 1.0]]), np.array([0.1]), G, h, ids, 0, 3, point_h, point_bound)
    assert m == 1 and ids[0] == 3 and point_h[0] == 1.0
    # the true clearance the rule takes as certain: h - k u - calibration
    assert point_bound[0] == pytest.approx(1.0 - 2.0 * 0.1 - 0.05)
    np.testing.assert_allclose(G[0], [0.0, 0.0, -1.0])
    assert h[0] == pytest.approx(20.0 * (1.0 - 0.5 - 2.0 * 0.1 - 0.05))
    # below the margin the recovery is capped at max_recovery
    m = fill_point_barrier(b.params(), np.zeros((1, 3)), np.eye(3)[None], 0, 1, np.array([-3.0]),
                           np.array([[0.0, 0.0, 1.0]]), np.zeros(1), G, h, ids, 0, 0, point_h, point_bound)
    assert h[0] == -5.0


def test_rows_out_of_reach_are_screened_and_infinity_means_no_boundary_and_nan_refuses():
    b = PointBarrier("g", "f", screen_reach_mm=1.0, always_first=1)
    G, h, ids = buffers(3, 3)
    P, J = np.zeros((3, 3)), np.tile(np.eye(3), (3, 1, 1))
    g = np.tile([0.0, 0.0, 1.0], (3, 1))
    # point 0 far but always kept, point 1 far (left out), point 2 near
    point_h, point_bound = np.zeros(3), np.zeros(3)
    assert fill_point_barrier(b.params(), P, J, 0, 3, np.array([5.0, 5.0, 1.0]), g, np.zeros(3), G, h, ids, 0, 0,
                              point_h, point_bound) == 2
    np.testing.assert_array_equal(ids[:2], [0, 2])
    np.testing.assert_array_equal(point_bound, [5.0, 5.0, 1.0])  # screened-out points keep their bound
    assert fill_point_barrier(b.params(), P, J, 0, 3, np.array([np.inf, 1.0, 1.0]), g, np.zeros(3), G, h, ids, 0, 0,
                              point_h, point_bound) == 2 and point_h[0] == np.inf and point_bound[0] == np.inf
    assert fill_point_barrier(b.params(), P, J, 0, 3, np.array([np.nan, 1.0, 1.0]), g, np.zeros(3), G, h, ids, 0, 0,
                              point_h, point_bound) == -NON_FINITE_FIELD
    # a keep-out reads the field from outside: +inf is inside the keep-out, a fault
    assert fill_point_barrier(KeepOut("g", "f").params(), P, J, 0, 3, np.array([np.inf, -1.0, -1.0]), g, np.zeros(3),
                              G, h, ids, 0, 0, point_h, point_bound) == -NON_FINITE_FIELD


def translated(pending):
    """(R_WI_end, p_WI_end, pending) of a shaft along x whose joints translate it (J = I):
    the end pose is the first-order one, moved by the rows' sum."""
    return np.eye(3), pending.sum(axis=0) if len(pending) else np.zeros(3), pending


def test_the_rcm_rows_hold_the_trocar_and_correct_a_lateral_error():
    # shaft along x through the origin; the trocar 0.1 mm off along y: b = gain * 0.1 on the y row
    A, b = np.zeros((2, 3)), np.zeros(2)
    c = RcmEquality(np.array([0.0, 0.1, 0.0]), gain_per_s=50.0)
    assert fill_rcm(c.params(), np.eye(3)[None], 0, np.eye(3), np.zeros(3), *translated(np.zeros((0, 3))), A, b, 0) == 2
    np.testing.assert_allclose(A, [[0, 1, 0], [0, 0, 1]])
    np.testing.assert_allclose(b, [5.0, 0.0])
    # the actuator still moves the point 0.06 mm towards the trocar and 0.02 mm along z (two
    # pending rows, J = I): the rows correct what is left after that motion
    pending = np.array([[0.0, 0.04, 0.02], [0.3, 0.02, 0.0]])
    assert fill_rcm(c.params(), np.eye(3)[None], 0, np.eye(3), np.zeros(3), *translated(pending), A, b, 0) == 2
    np.testing.assert_allclose(b, [50.0 * 0.04, 50.0 * -0.02])
    # the pending motion carries the shaft 0.3 mm further off (y) and 0.4 mm (z): a correction
    # of 50 x 0.5 = 25 mm/s > the max, a planned stop (the rows written all the same)
    far = RcmEquality(np.array([0.0, 0.0, 0.0]), gain_per_s=50.0, max_correction_mm_s=20.0)
    away = np.array([[0.0, -0.3, -0.4]])
    code = fill_rcm(far.params(), np.eye(3)[None], 0, np.eye(3), np.zeros(3), *translated(away), A, b, 0)
    assert code == -CANNOT_HOLD
    np.testing.assert_allclose(b, [15.0, 20.0])
    assert far.fault_reason(CANNOT_HOLD) == "actuator cannot hold the trocar"
    # the same error today, at rest (nothing pending, or the motion brings the shaft back): corrected at the gain
    offset = RcmEquality(np.array([0.0, 0.3, 0.4]), gain_per_s=50.0, max_correction_mm_s=20.0)
    for pending, want in ((np.zeros((0, 3)), [15.0, 20.0]), (np.array([[0.0, 0.1, 0.1]]), [10.0, 15.0])):
        assert fill_rcm(offset.params(), np.eye(3)[None], 0, np.eye(3), np.zeros(3), *translated(pending), A, b, 0) == 2
        np.testing.assert_allclose(b, want)


@given(st.floats(-0.5, 0.5), st.floats(5.0, 40.0))
def test_the_rcm_predicts_the_mean_of_the_first_order_and_the_end_pose(theta, lever):
    """The pending motion turns the shaft by theta (rad) about z through a point `lever` mm
    behind the trocar, which lies on the shaft now: to first order the pivot leaves the
    trocar by lever theta; at the end pose the trocar lies lever |sin theta| off the shaft,
    lever sin theta cos theta along the present lateral y. The correction is the mean."""
    A, b = np.zeros((2, 1)), np.zeros(2)
    c = RcmEquality(np.array([lever, 0.0, 0.0]), gain_per_s=50.0, max_correction_mm_s=20.0)
    J = np.array([[[0.0], [lever], [0.0]]])  # the trocar's material point on a joint about z through the origin
    R_end = np.array([[np.cos(theta), -np.sin(theta), 0.0], [np.sin(theta), np.cos(theta), 0.0], [0.0, 0.0, 1.0]])
    code = fill_rcm(c.params(), J, 0, np.eye(3), np.zeros(3), R_end, np.zeros(3), np.array([[theta]]), A, b, 0)
    np.testing.assert_allclose(b, [50.0 * 0.5 * (-lever * theta - lever * np.sin(theta) * np.cos(theta)), 0.0],
                               atol=1e-12)
    first, end = lever * abs(theta), lever * abs(np.sin(theta))  # now: 0
    if min(abs(50.0 * first - 20.0), abs(first - GROWTH_TOL_MM)) > 1e-9:  # away from the rule's edges
        assert (code == -CANNOT_HOLD) == (first > GROWTH_TOL_MM and 50.0 * first > 20.0)  # end <= first here


@given(st.floats(1.0, 100.0), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0),
       st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(1.0, 50.0))
def test_the_rcm_stops_exactly_on_its_two_rules(gain, ey, ez, dy, dz, fy, fz, vmax):
    """The trocar (0, ey, ez) off a shaft along x; the pending motion moves its point by
    (dy, dz) to first order (J = I) and ends with the trocar (fy, fz) off the shaft: the
    rows correct the mean; the step stops when either offset grows (by more than
    GROWTH_TOL_MM) past its threshold, vmax / gain to first order, BRAKING_FACTOR times
    that at the end pose."""
    A, b = np.zeros((2, 3)), np.zeros(2)
    c = RcmEquality(np.array([0.0, ey, ez]), gain_per_s=gain, max_correction_mm_s=vmax)
    pending = np.array([[0.0, dy, dz]])
    p_end = np.array([0.0, ey - fy, ez - fz])
    code = fill_rcm(c.params(), np.eye(3)[None], 0, np.eye(3), np.zeros(3), np.eye(3), p_end, pending, A, b, 0)
    now, first, end = np.hypot(ey, ez), np.hypot(ey - dy, ez - dz), np.hypot(fy, fz)
    np.testing.assert_allclose(b, gain * 0.5 * np.array([ey - dy + fy, ez - dz + fz]), atol=1e-12)
    edges = (first - now - GROWTH_TOL_MM, gain * first - vmax, end - now - GROWTH_TOL_MM,
             gain * end - BRAKING_FACTOR * vmax)
    if min(abs(x) for x in edges) > 1e-9:
        stop = (first > now + GROWTH_TOL_MM and gain * first > vmax) or \
               (end > now + GROWTH_TOL_MM and gain * end > BRAKING_FACTOR * vmax)
        assert (code == -CANNOT_HOLD) == stop


def test_the_filters_rcm_stops_at_the_speed_the_tip_can_move_in_every_direction():
    from safety.filter import rcm_constraint
    # the tip speed polytope holds the ball of radius v_max / REACH (its faces' distance)
    assert RcmEquality(np.zeros(3), 200.0).max_correction_mm_s == pytest.approx(20.0 / REACH)
    c = rcm_constraint(FilterConfig(max_tip_speed_mm_s=10.0), [1.0, 2.0, 3.0], 200.0)
    assert c.max_correction_mm_s == pytest.approx(10.0 / REACH) and c.gain_per_s == 200.0
    np.testing.assert_array_equal(c.p_WC, [1.0, 2.0, 3.0])


def test_joint_bounds_intersect():
    from safety.constraints.joint_limits import fill_joint_position
    from safety.constraints.joint_speed import fill_joint_speed

    lb, ub = np.full(2, -np.inf), np.full(2, np.inf)
    fill_joint_speed(JointSpeedLimits(np.array([1.0, 2.0])).params(), lb, ub)
    # joint 0 0.05 rad from its upper limit (margin 0): ub = gain * 0.05 = 0.5 rad/s
    c = JointPositionLimits(np.array([-1.0, -1.0]), np.array([1.0, 1.0]), gain_per_s=10.0, margin_rad=0.0)
    fill_joint_position(c.params(), np.array([0.95, 0.0]), lb, ub)
    np.testing.assert_allclose(lb, [-1.0, -2.0])
    np.testing.assert_allclose(ub, [0.5, 2.0])


@njit(cache=True)
def fill_unknown(sp, weird, G, h, ids, m, id0):
    return m


def test_the_assembly_refuses_what_it_cannot_wire():
    class Weird(TipSpeedLimit):
        filler = staticmethod(fill_unknown)

    with pytest.raises(ValueError, match="unknown argument 'weird'"):
        ConstraintStack([Weird()], {}, {}, FilterConfig(), n_joints=3)
    with pytest.raises(ValueError, match="point group 'nowhere'"):
        ConstraintStack([PointBarrier("nowhere", "eye")], {"boundary": 2}, {"eye": fill_unknown}, FilterConfig())
    with pytest.raises(ValueError, match="no field kernel for slot 'eye'"):
        ConstraintStack([PointBarrier("boundary", "eye")], {"boundary": 2}, {}, FilterConfig())
    with pytest.raises(ValueError, match="module-level numba"):
        ConstraintStack([PointBarrier("boundary", "eye")], {"boundary": 2}, {"eye": lambda fp, P: None}, FilterConfig())


def test_the_rcm_constraint_and_the_robots_rcm_rows_agree():
    # the constraint's rows on the loop's kinematics equal the plant's (planning's IK uses those)
    from planning import SurgeryScenario, start_posture
    from planning.instrument_points import instrument_points
    from planning.robot import RCM_GAIN_PER_S, Robot

    scenario = SurgeryScenario()
    robot = Robot(scenario)
    q0 = start_posture(robot, scenario.eye_pose.p_WE, scenario.p_WC)
    c = RcmEquality(np.asarray(scenario.p_WC, dtype=float), RCM_GAIN_PER_S, max_correction_mm_s=1e9)  # uncapped
    for q in q0 + 0.02 * np.random.default_rng(0).standard_normal((5, 6)):
        ip = instrument_points(robot, q, scenario.p_WC)
        A, b = np.zeros((2, 6)), np.zeros(2)
        fill_rcm(c.params(), ip.J_C[None], 0, ip.R_WI, ip.p_WI, ip.R_WI, ip.p_WI, np.zeros((0, 6)), A, b, 0)
        A_ref, b_ref = robot.rcm_rows(q, scenario.p_WC, RCM_GAIN_PER_S)
        np.testing.assert_allclose(A, A_ref, atol=1e-9)
        np.testing.assert_allclose(b, b_ref, atol=1e-9)


def test_the_end_pose_is_the_present_one_when_a_pending_row_is_not_finite():
    from safety.constraints.rcm import displaced

    q = np.array([0.1, -0.2, 0.3])
    two = np.array([[0.01, 0.0, 0.0], [0.0, 0.02, -0.01]])
    np.testing.assert_allclose(displaced(q, two), [0.11, -0.18, 0.29], atol=1e-15)
    np.testing.assert_array_equal(displaced(q, np.array([[0.01, np.nan, 0.0]])), q)
    np.testing.assert_array_equal(displaced(q, np.zeros((0, 3))), q)
