"""Peripheral planning on a fitted model: band geometry, constraints at every waypoint,
continuity, coverage on a known case, reasons, bad input."""
from __future__ import annotations

import numpy as np
import pytest

from models import Ellipsoid
from planning import Robot, SurgeryScenario
from planning.peripheral import (SHAFT_CHECK_DT_S, SHAFT_SLACK_MM, Band, BandSpec, coverage, shaft_clearances_mm, plan_band, plan_path,
                                 port_roll_rad, serpentine)

SPEC = BandSpec(z_min_E=0.0, z_max_E=3.0, spacing_mm=1.0)


@pytest.fixture(scope="module")
def setup():
    scenario = SurgeryScenario()
    robot = Robot(scenario)
    model = scenario.eye.ellipsoid  # a fitted model would differ by micrometres (the ellipsoid fit's MAE)
    return scenario, robot, model, plan_path(robot, scenario, model, SPEC)


def test_band_cells_lie_on_the_model_in_the_band(setup):
    scenario, robot, model, plan = setup
    band = plan.band
    z = scenario.eye_pose.to_E(band.surface_W.reshape(-1, 3))[:, 2].reshape(band.surface_W.shape[:2])
    np.testing.assert_allclose(z, np.broadcast_to(band.z_E[:, None], z.shape), atol=1e-6)
    np.testing.assert_allclose(model.signed_distance(band.surface_W.reshape(-1, 3)), 0.0, atol=1e-6)
    np.testing.assert_allclose(model.signed_distance(band.target_W.reshape(-1, 3)), SPEC.standoff_mm, atol=1e-6)


def test_every_waypoint_meets_rcm_port_lens_and_margin(setup):
    scenario, robot, model, plan = setup
    assert len(plan.waypoints_W) >= 20 and plan.band.reachable.any()
    ts = np.arange(plan.trajectory.start_time(), plan.trajectory.end_time(), 0.01)
    Q = plan.trajectory.vector_values(ts).T
    assert max(robot.rcm_error_mm(q, scenario.p_WC) for q in Q) <= 0.005  # the spline between IK waypoints
    assert np.degrees(min(robot.joint_margin_rad(q).min() for q in Q)) >= SPEC.min_margin_deg - 0.5
    assert np.abs(np.diff(Q, axis=0)).max() < 0.05  # continuous: no branch flip within 10 ms
    speed = np.abs(plan.trajectory.derivative(1).vector_values(ts)).T / robot.qdot_max
    assert speed.max() <= 1.0
    tips = np.array([robot.pose("T", q)[1] for q in Q])
    assert model.signed_distance(tips).min() >= SPEC.standoff_mm - 0.05
    assert plan.band.port_deg[plan.band.reachable].max() <= SPEC.port_max_deg
    for p, roll, (r, i) in zip(plan.waypoints_W, plan.roll_rad, serpentine(plan.band)):
        n = plan.band.normal_W[r, i]
        assert roll == pytest.approx(port_roll_rad(p, scenario.p_WC, n))


def test_the_planned_path_covers_the_reachable_band(setup):
    scenario, robot, model, plan = setup
    ts = np.arange(plan.trajectory.start_time(), plan.trajectory.end_time(), 0.02)
    tips = np.array([robot.pose("T", q)[1] for q in plan.trajectory.vector_values(ts).T])
    assert coverage(plan.band, tips, SPEC.spacing_mm) >= 0.9


def test_coverage_of_a_known_case():
    """Ten cells on a line 1 mm apart; a path over the first six covers 60 %."""
    T = np.column_stack([np.arange(10.0), np.zeros(10), np.zeros(10)])[None]
    band = Band(np.arange(10.0), np.zeros(1), T, np.zeros_like(T), T, np.full((1, 10), "ok", dtype=object), np.zeros((1, 10)))
    assert coverage(band, T[0, :6], 1.0) == pytest.approx(0.6)


def test_unreachable_cells_say_why(setup):
    scenario, robot, model, plan = setup
    reasons = set(plan.band.reason.ravel())
    assert reasons <= {"ok", "lens", "port", "reach", "shaft"} and {"ok", "port"} <= reasons


@pytest.mark.parametrize("kw, message", [({"standoff_mm": 0.5}, "standoff_mm"), ({"z_min_E": 3.0, "z_max_E": 1.0}, "z_min"),
                                         ({"spacing_mm": 0.0}, "spacing_mm")])
def test_bad_band_specs_are_refused(kw, message):
    with pytest.raises(ValueError, match=message):
        BandSpec(**kw)


def test_a_band_outside_the_model_is_refused(setup):
    scenario, robot, model, _ = setup
    with pytest.raises(ValueError, match="outside the model"):
        plan_band(robot, scenario, model, BandSpec(z_min_E=8.0, z_max_E=11.0))
    small = Ellipsoid(model.center, [3.5, 3.5, 3.5], model.rotation)  # the band must end 1 mm (standoff) inside it
    with pytest.raises(ValueError, match="outside the model"):
        plan_band(robot, scenario, small, SPEC)


def test_a_wide_boundary_drops_the_cells_where_the_shaft_would_cross_it(setup):
    """With the sphere phase's boundary (0.5 + 1 mm) on the default band, some postures, and
    some ways between neighbouring cells, bring a shaft point near the trocar inside it:
    those cells say "shaft", and the timed path's shaft points keep boundary + slack
    everywhere (the check's own samples exactly; between them the shaft point moves at
    most |v| dt: 20 mm/s x 5 ms = 0.1 mm, a bound on any joint-limited instrument point here)."""
    scenario, robot, model, plan = setup
    spec = BandSpec(z_min_E=0.0, z_max_E=5.0, spacing_mm=1.0, standoff_mm=1.7, boundary_mm=1.5)
    wide = plan_path(robot, scenario, model, spec)
    assert (wide.band.reason == "shaft").any() and wide.band.reachable.any()
    traj, limit = wide.trajectory, spec.boundary_mm + SHAFT_SLACK_MM
    on_grid = np.arange(traj.start_time(), traj.end_time(), SHAFT_CHECK_DT_S)
    assert shaft_clearances_mm(robot, traj.vector_values(on_grid).T, scenario.p_WC, model).min() >= limit
    off_grid = np.arange(traj.start_time() + 0.5e-3, traj.end_time(), 1e-3)
    assert shaft_clearances_mm(robot, traj.vector_values(off_grid).T, scenario.p_WC, model).min() >= limit - 0.1
    # on the narrow boundary no posture of the default plan comes near it
    ts = np.arange(plan.trajectory.start_time(), plan.trajectory.end_time(), 1e-3)
    assert shaft_clearances_mm(robot, plan.trajectory.vector_values(ts).T, scenario.p_WC, model).min() >= 0.7


def test_a_standoff_inside_the_boundary_is_refused():
    with pytest.raises(ValueError, match="standoff_mm"):
        BandSpec(standoff_mm=1.2, boundary_mm=1.5)
    with pytest.raises(ValueError, match="boundary_mm"):
        BandSpec(boundary_mm=0.3)
