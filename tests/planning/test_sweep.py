"""One trocar's sweep: the first look along the tip's segment between cells, the shaft's
lens clearance, the serpentine's two pairs of end cells."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models import Sphere
from planning.peripheral import Band, serpentine
from planning.sweep import CHORD_STEP_MM, chord_postures, lens_clearances_mm


def test_chord_postures_put_the_tip_on_the_segment_and_the_shaft_through_the_trocar(setup):
    scenario, robot, q_a = setup
    p_a = robot.pose("T", q_a)[1]
    p_b = scenario.eye_pose.to_W(np.array([[3.0, 1.0, -2.0]]))[0]  # 2.4 mm away, mid-vitreous
    tips, Q = chord_postures(robot, p_a, p_b, scenario.p_WC, q_a, q_a)
    n = len(tips) + 1
    assert n >= int(np.ceil(np.linalg.norm(p_b - p_a) / CHORD_STEP_MM)) and len(Q) == len(tips)
    f = (tips - p_a) @ (p_b - p_a) / np.linalg.norm(p_b - p_a) ** 2
    np.testing.assert_allclose(f, np.arange(1, n) / n, atol=1e-12)  # evenly inside, ends excluded
    for p, q in zip(tips, Q):
        np.testing.assert_allclose(robot.pose("T", q)[1], p, atol=1e-6)  # closed-form IK: exact
        assert robot.rcm_error_mm(q, scenario.p_WC) < 1e-6


def test_lens_clearance_of_a_shaft_passing_a_sphere():
    """A segment from (2, 0, 5) to (2, 0, -5) passes 2 mm from the centre of a 1 mm sphere:
    1 mm clear, to within the sampling's sagitta (32 samples, 0.32 mm apart: < 0.01 mm);
    through the centre it crosses 1 mm deep (less by up to half a spacing); a shaft along z = 5 keeps 4 mm."""
    lens = Sphere(np.zeros(3), 1.0)
    c = lens_clearances_mm(lens, np.array([2.0, 0.0, 5.0]), np.array([[2.0, 0.0, -5.0]]))
    assert c[0] == pytest.approx(1.0, abs=0.01) and c[0] >= 1.0
    c = lens_clearances_mm(lens, np.array([0.0, 0.0, 5.0]), np.array([[0.0, 0.0, -5.0], [3.0, 0.0, 5.0]]))
    assert -1.0 <= c[0] <= -1.0 + 5.0 / 31 + 1e-9  # the nearest sample lies within half a spacing of the centre
    assert c[1] == pytest.approx(4.0, abs=1e-9)  # along z = 5: nearest at the trocar, 5 mm from the centre


def _band(mask: np.ndarray) -> Band:
    rings, n_az = mask.shape
    z = np.zeros((rings, n_az, 3))
    return Band(np.linspace(0, 2 * np.pi, n_az, endpoint=False), np.arange(float(rings)), z, z, z,
                np.where(mask, "ok", "reach").astype(object), np.zeros(mask.shape))


@settings(max_examples=40)
@given(st.lists(st.lists(st.booleans(), min_size=8, max_size=8), min_size=1, max_size=4))
def test_the_flipped_serpentine_visits_the_same_cells_each_ring_the_other_way(rows):
    mask = np.array(rows, dtype=bool)
    band = _band(mask)
    a, b = serpentine(band), serpentine(band, flip=True)
    assert sorted(a) == sorted(b) == sorted(map(tuple, np.argwhere(mask).tolist()))
    for r in range(mask.shape[0]):
        ring_a, ring_b = [c for c in a if c[0] == r], [c for c in b if c[0] == r]
        assert ring_b == ring_a[::-1]


def test_a_cell_straight_below_the_trocar_is_not_swept_rather_than_an_error(setup):
    """The roll convention (planning.ik.roll_direction_W) has no roll for a vertical shaft:
    such a cell is left out like one the arm cannot reach (IKFailure when it is the only one)."""
    from models import Ellipsoid
    from planning.ik import IKFailure
    from planning.peripheral import BandSpec
    from planning.sweep import plan_sweep

    scenario, robot, _ = setup
    t = scenario.p_WC - np.array([0.0, 0.0, 6.0])
    cell = np.broadcast_to(t, (1, 1, 3)).copy()
    band = Band(np.zeros(1), np.zeros(1), cell, np.broadcast_to([0.0, 0.0, 1.0], (1, 1, 3)).copy(), cell,
                np.full((1, 1), "ok", dtype=object), np.zeros((1, 1)))
    eye = scenario.eye
    model = Ellipsoid(eye.pose.p_WE, eye.radii, eye.pose.R_WE)
    with pytest.raises(IKFailure):
        plan_sweep(robot, band, scenario.p_WC, model, BandSpec(), [(0, 0)])


def test_a_cell_whose_shaft_crosses_the_lens_on_the_way_is_dropped_as_lens(setup):
    """Three mid-vitreous cells 2 mm apart, far from the retina; a 0.3 mm keep-out sphere
    on the straight shaft to the third, 60 % of the way in: that shaft crosses it, the
    second cell's passes 2 mm x 0.6 - 0.3 mm = 0.9 mm from it (> LENS_CLEARANCE_MM 0.5 mm).
    The third cell is dropped for the lens, not the shaft; the other two are swept."""
    from models import Ellipsoid
    from planning.peripheral import BandSpec
    from planning.sweep import plan_sweep

    scenario, robot, _ = setup
    T = scenario.eye_pose.to_W(np.array([[1.0, -2.0, -3.0], [1.0, 0.0, -3.0], [1.0, 2.0, -3.0]]))
    N = T - scenario.eye_pose.p_WE
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    band = Band(np.zeros(3), np.zeros(1), T[None].copy(), N[None].copy(), T[None].copy(),
                np.full((1, 3), "ok", dtype=object), np.zeros((1, 3)))
    lens = Sphere(scenario.p_WC + 0.6 * (T[2] - scenario.p_WC), 0.3)
    eye = scenario.eye
    model = Ellipsoid(eye.pose.p_WE, eye.radii, eye.pose.R_WE)
    sweep = plan_sweep(robot, band, scenario.p_WC, model, BandSpec(), [(0, 0), (0, 1), (0, 2)], lens_W=lens)
    assert sweep.dropped == {(0, 2): "lens"}
    assert sweep.cells == [(0, 0), (0, 1)]
    assert lens_clearances_mm(lens, scenario.p_WC, sweep.targets_W).min() >= 0.5


def test_a_midpoint_straight_below_the_trocar_is_solved_without_a_roll(setup):
    """Two targets 6 mm below the trocar, 1 mm either side (shafts 9.5 deg off vertical, each
    with a roll): the chord's midpoint puts the shaft vertical, where the roll convention
    has none; the scan solves it from the neighbours' mean posture instead of failing, and
    the trajectory still holds the RCM and the tip on the chord (0.5 um checks)."""
    from planning.scan import plan_ik_scan

    scenario, robot, _ = setup
    P = scenario.p_WC + np.array([[1.0, 0.0, -6.0], [-1.0, 0.0, -6.0]])
    traj, P_used, _ = plan_ik_scan(robot, P, scenario.p_WC, 2.0, roll_rad=np.array([0.3, 0.3]))
    ts = np.linspace(traj.start_time(), traj.end_time(), 41)
    for q in traj.vector_values(ts).T:
        assert robot.rcm_error_mm(q, scenario.p_WC) < 0.01  # 0.5 um at the checks, the spline between them
    np.testing.assert_allclose(robot.pose("T", traj.value(traj.end_time()).ravel())[1], P[-1], atol=1e-6)


def test_a_cell_whose_way_swings_a_joint_into_its_margin_is_dropped_as_reach(setup):
    """The timed path between cells is a spline, which can swing a joint past the margin its
    cells keep: a way through a posture with J6 1 deg from its limit (a roll: the tip and
    the shaft stay where they are) drops the cell it leads to as "reach", not the one it
    leaves; the same way with J6 10 deg inside the margin drops none."""
    from pydrake.trajectories import PiecewisePolynomial

    from models import Ellipsoid
    from planning.sweep import _cells_too_near_on_the_way

    scenario, robot, q = setup
    eye = scenario.eye
    model = Ellipsoid(eye.pose.p_WE, eye.radii, eye.pose.R_WE)
    tip = robot.pose("T", q)[1]
    margin = np.radians(5.0)
    for j6_margin_deg, expected in ((1.0, {1: "reach"}), (15.0, {})):
        q_way = q.copy()
        q_way[5] = robot.q_upper[5] - np.radians(j6_margin_deg)
        traj = PiecewisePolynomial.FirstOrderHold([0.0, 0.5, 1.0], np.array([q, q_way, q]).T)
        P_used = np.array([tip, tip + 1e-3, tip + 2e-3])  # the cells and a midpoint between them
        out = _cells_too_near_on_the_way(robot, traj, P_used, P_used[[0, 2]], scenario.p_WC, model, 0.7, margin)
        assert out == expected
