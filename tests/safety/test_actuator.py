"""The actuator model the filter is told, and the actuator-aware barrier on a toy robot
whose joints are the tip's Cartesian coordinates (J = I, mm/rad) in a spherical retina."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models import Sphere
from safety import ConstraintStack, FilterConfig
from safety.actuator import ActuatorModel
from safety.constraints import PointBarrier
from safety.constraints.actuated_barrier import CANNOT_BRAKE, ActuatedPointBarrier, braking_margins, fill_actuated_barrier
from safety.tabulated_field import tabulate, tabulated_kernel

DT = 1e-3
EYE = Sphere(np.zeros(3), 12.0)


def braking_path(model: ActuatorModel, v, queued, steps: int = 6000) -> np.ndarray:
    """(k, n) the joints' displacement (rad) after each step of the queue and of the braking
    after it (every command after the queue zero), simulated."""
    v, q, path = np.array(v, dtype=float), np.zeros(len(v)), []
    for target in list(np.atleast_2d(queued)) + [np.zeros(len(v))] * steps:
        v = model.advance(v, target, DT)
        q = q + DT * v
        path.append(q)
        if len(path) > len(np.atleast_2d(queued)) and not np.any(v):
            break
    return np.array(path)


def braking_displacement(model: ActuatorModel, v, queued) -> np.ndarray:
    """The joints' whole displacement (rad) when every command after the queue is zero."""
    return braking_path(model, v, queued)[-1]


def test_the_ideal_actuator_applies_the_command():
    m = ActuatorModel()
    assert m.ideal and m.delay_steps(DT) == 0 and m.alpha(DT) == 1.0
    np.testing.assert_array_equal(m.advance(np.ones(6), np.arange(6.0), DT), np.arange(6.0))
    np.testing.assert_allclose(m.pending_rows(np.zeros(6), np.ones((1, 6)), DT), [np.full(6, DT), np.zeros(6)])


@settings(max_examples=40)
@given(st.floats(0.0, 0.03), st.integers(0, 6), st.lists(st.floats(-0.2, 0.2), min_size=3, max_size=3),
       st.integers(0, 2 ** 31))
def test_the_pending_rows_add_up_to_the_braking_displacement(lag_s, delay, v, seed):
    m = ActuatorModel(delay * DT, lag_s)
    queued = np.random.default_rng(seed).uniform(-0.2, 0.2, (delay + 1, 3))
    rows = m.pending_rows(np.array(v), queued, DT)
    # a linear lag of unit gain: the rows' sum is the whole braking, to the simulation's tail
    np.testing.assert_allclose(rows.sum(axis=0), braking_displacement(m, v, queued), atol=1e-9)


def test_an_acceleration_limit_brakes_within_its_row():
    a = 2.0  # rad/s^2
    m = ActuatorModel(accel_limit_rad_s2=a)
    v = np.array([0.3, -0.2, 0.0])
    rows = m.pending_rows(v, np.zeros((1, 3)), DT)
    # the queued zero's step: the fastest joint slows by a dt, all joints alike
    v1 = v * (1.0 - a * DT / 0.3)
    np.testing.assert_allclose(rows[0], DT * v1)
    # then every joint brakes in max|v1| / a: v1 max|v1| / (2 a), the discrete ramp adding at most v1 dt / 2
    np.testing.assert_allclose(rows[1], v1 * (0.3 - a * DT) / (2 * a) + v1 * DT / 2)
    total = braking_displacement(m, v, np.zeros((1, 3)))
    assert np.all(np.abs(total) <= np.abs(rows.sum(axis=0)) + 1e-15)


@settings(max_examples=60)
@given(st.sampled_from([0.0, 0.005, 0.01]), st.sampled_from([0.0, 0.02, 0.05]), st.floats(2.0, 60.0),
       st.floats(0.01, 3.0), st.booleans(), st.integers(0, 2 ** 31))
def test_no_joint_direction_brakes_past_the_rows_inward_parts(delay_s, lag_s, accel, speed, roll, seed):
    # the barrier's bound on a point's approach (safety.constraints.actuated_barrier) holds if, along any
    # joint direction u, the braking path never goes further than the rows' positive parts along u
    m = ActuatorModel(delay_s, lag_s, accel)
    rng = np.random.default_rng(seed)
    v, queued = speed * rng.uniform(-1, 1, 6), speed * rng.normal(size=(m.delay_steps(DT) + 1, 6))
    if roll:  # the search adversary's commands: a fast wrist roll beside slow positioning joints
        v[5] = queued[:, 5] = 3.0
    rows, path = m.pending_rows(v, queued, DT), braking_path(m, v, queued)
    U = rng.normal(size=(64, 6))
    U /= np.linalg.norm(U, axis=1)[:, None]
    reach = np.maximum(path @ U.T, 0.0).max(axis=0)
    bound = np.maximum(rows @ U.T, 0.0).sum(axis=0)
    assert np.all(reach <= bound + 1e-12 * (1.0 + bound))


def test_a_fast_roll_in_the_queue_is_braked_from_the_velocity_it_reaches():
    # 5 ms delay, 20 ms lag, 1000 deg/s^2: the fault campaign's actuator; a 3 rad/s roll queued beside a slow
    # positioning joint; counting each queued command at dt x command misses the braking it adds
    m = ActuatorModel(0.005, 0.02, np.radians(1000.0))
    v = np.array([0.0, 0.02, 0.0, 0.0, 0.0, 3.0])
    queued = np.tile([0.0, 0.3, 0.0, 0.0, 0.0, 3.0], (m.delay_steps(DT) + 1, 1))
    travel = braking_path(m, v, queued)[-1, 1]
    rows = m.pending_rows(v, queued, DT)
    assert rows[:, 1].sum() >= travel
    counted_at_command = DT * queued[:, 1].sum() + 0.02 * (0.02 + 3.0 / (2 * np.radians(1000.0)))
    assert counted_at_command < 0.8 * travel


@pytest.mark.parametrize("kw", [dict(delay_s=-0.001), dict(lag_s=np.nan), dict(accel_limit_rad_s2=0.0),
                                dict(accel_limit_rad_s2=np.nan), dict(lag_s=2.0)])
def test_bad_actuator_parameters_are_refused(kw):
    with pytest.raises(ValueError, match="ActuatorModel"):
        ActuatorModel(**kw)


def test_the_barrier_keeps_the_braking_travel_towards_the_wall_in_its_margin():
    b = ActuatedPointBarrier("g", "f", d_safe_mm=0.5, gain_per_s=20.0, curvature_radius_mm=5.0, revolute_joints=False,
                             sigma_factor=3.0)
    G, h, ids = np.zeros((1, 3)), np.zeros(1), np.zeros(1, dtype=np.int64)
    point_h, point_bound = np.zeros(1), np.zeros(1)
    pending = np.array([[0.0, 0.0, -0.2], [0.0, 0.0, 0.3]])  # 0.2 mm towards the wall, 0.3 mm away
    m = fill_actuated_barrier(b.params(), np.zeros((1, 3)), np.eye(3)[None], 0, 1, np.array([1.0]),
                              np.array([[0.0, 0.0, 1.0]]), np.zeros(1), pending, G, h, ids, 0, 0, point_h, point_bound)
    margin = 0.2 + 0.5 ** 2 / (2 * 5.0)  # the inward part only, and the curvature over the 0.5 mm of travel
    assert m == 1 and point_h[0] == 1.0  # the reported clearance is the present one
    assert point_bound[0] == 1.0  # and so is the bound on the true clearance (sigma 0 here)
    np.testing.assert_allclose(G[0], [0.0, 0.0, -1.0])
    assert h[0] == pytest.approx(20.0 * (1.0 - margin - 0.5))
    fill_actuated_barrier(b.params(), np.zeros((1, 3)), np.eye(3)[None], 0, 1, np.array([1.0]),
                          np.array([[0.0, 0.0, 1.0]]), np.array([0.05]), pending, G, h, ids, 0, 0, point_h, point_bound)
    assert point_bound[0] == pytest.approx(1.0 - 3.0 * 0.05)
    # within the margin at present, past it once braked: a planned stop
    m = fill_actuated_barrier(b.params(), np.zeros((1, 3)), np.eye(3)[None], 0, 1, np.array([0.55]),
                              np.array([[0.0, 0.0, 1.0]]), np.zeros(1), pending[:1], G, h, ids, 0, 0, point_h,
                              point_bound)
    assert m == -CANNOT_BRAKE
    assert b.fault_reason(CANNOT_BRAKE) == "actuator cannot brake before the boundary"


def test_turning_joints_add_the_second_order_of_the_kinematics():
    # one revolute joint at the origin about z, the point 10 mm along x: J = [0, 10, 0];
    # a pending turn of 0.05 rad moves it 10 (1 - cos 0.05) = 0.0125 mm off the tangent,
    # within 1/2 0.05^2 x 10 = 0.0125 mm (the bound is exact to second order here)
    J = np.array([[[0.0], [10.0], [0.0]]])
    out = np.zeros(1)
    braking_margins(1.0, np.array([[10.0, 0.0, 0.0]]), J, 0, 1, np.array([5.0]), np.array([[0.0, 1.0, 0.0]]),
                    np.array([[0.05]]), 0.0, 1.0, out)
    # the first order: 0.5 mm along +y (away from the wall: no margin); the second order
    assert out[0] == pytest.approx(0.5 * 0.05**2 * 10.0)
    assert 10.0 * (1 - np.cos(0.05)) <= out[0] + 1e-9


def push(barrier, model: ActuatorModel, seconds: float = 1.5, speed: float = 20.0):
    """Push the toy tip straight at the wall from 3 mm clearance through `model`; the true
    clearances and the filter's refusals."""
    config = FilterConfig(calibration_bound_mm=0.0, calibration_bound_deg=0.0)
    stack = ConstraintStack([barrier], {"boundary": 1}, {"eye": tabulated_kernel}, config, n_joints=3)
    p, v, last = np.array([0.0, 0.0, -9.0]), np.zeros(3), np.zeros(3)
    queue = [np.zeros(3)] * model.delay_steps(DT)
    clear, refused = [], []
    for k in range(int(seconds / DT)):
        pending = model.pending_rows(v, np.array(queue + [last]), DT)
        h, g = EYE.signed_distance(p[None]), EYE.gradient(p[None])
        out, _ = stack.solve(p.copy(), np.array([0.0, 0.0, -speed, 0.0]), np.array([k * DT] * 3), np.eye(3),
                             np.zeros((0, 3)), p[None].copy(), np.eye(3)[None].copy(), np.array([[0, 1]]),
                             (tabulate(h, g, np.zeros(1)),), pending=pending)
        refused.append(not out.ok)
        queue.append(last)
        v = model.advance(v, queue.pop(0), DT)  # the actuator takes the last command (or the queue's oldest)
        last = out.qdot
        p = p + DT * v
        clear.append(float(EYE.signed_distance(p[None])[0]))
    return np.array(clear), np.array(refused)


@pytest.mark.parametrize("model", [ActuatorModel(lag_s=0.02), ActuatorModel(0.005, 0.02)])
def test_a_lagging_robot_keeps_the_margin_only_when_the_filter_knows_it(model):
    aware, _ = push(ActuatedPointBarrier("boundary", "eye", always_first=1, revolute_joints=False), model)
    naive, _ = push(PointBarrier("boundary", "eye", always_first=1), model)
    assert aware.min() >= 0.5 - 1e-3  # the braking travel is in the margin (linear field along the push)
    assert aware[-1] == pytest.approx(0.5, abs=0.02)  # and it still gets there
    assert naive.min() < 0.5 - 0.02  # the plain barrier overshoots by the lag's travel
