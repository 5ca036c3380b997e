"""Multi-port planning: every swept cell from a port that reaches it, the sweeps through
their own trocar clear of the boundary, switches outside the eye, regions, reasons."""
from __future__ import annotations

import numpy as np
import pytest

from models import Ellipsoid
from planning import SurgeryScenario
from planning.multiport import DEPRESSION_MM, combined_reason, plan_ports, regions
from planning.peripheral import SHAFT_SLACK_MM, BandSpec, cell_reasons, shaft_clearances_mm
from planning.ports import standard_ports
from planning.robot import Robot
from planning.scenario import PORTS_EYE_POSE

SPEC = BandSpec(z_min_E=0.0, z_max_E=2.0)


@pytest.fixture(scope="module")
def planned():
    ports = standard_ports("right")
    scenario = SurgeryScenario(eye_pose=PORTS_EYE_POSE, ports=ports, p_EC=None)
    robot = Robot(scenario)
    eye = scenario.eye
    model = Ellipsoid(eye.pose.p_WE, eye.radii, eye.pose.R_WE)  # the true retina as the fitted model
    return scenario, robot, model, plan_ports(robot, scenario, model, ports[:2], SPEC)


def test_each_swept_cell_is_swept_from_a_port_that_reaches_it(planned):
    scenario, robot, model, plan = planned
    for k, port in enumerate(plan.ports):
        assert np.all(plan.reasons_by_port[port.name][plan.port_of == k] == "ok")
    swept = {cell for seg in plan.segments for cell in seg.sweep.cells}
    assert len(swept) == int((plan.port_of >= 0).sum())  # no cell twice
    assert np.all(plan.band.reason[plan.port_of >= 0] == "ok") and np.all(plan.band.reason[plan.port_of < 0] != "ok")
    # the two working ports reach more than either alone
    assert (plan.port_of >= 0).sum() > max((r == "ok").sum() for r in plan.reasons_by_port.values()) * 0.9


def test_the_sweeps_pivot_about_their_own_trocar_and_keep_the_shaft_off_the_boundary(planned):
    scenario, robot, model, plan = planned
    for seg in plan.segments:
        assert np.linalg.norm(seg.p_WC - scenario.p_WC_of(seg.port.name)) < 1e-9
        traj = seg.sweep.trajectory
        ts = np.linspace(traj.start_time(), traj.end_time(), 200)
        Q = traj.vector_values(ts).T
        assert max(robot.rcm_error_mm(q, seg.p_WC) for q in Q) < 0.01  # 10 um: the spline between IK waypoints
        assert shaft_clearances_mm(robot, Q, seg.p_WC, model).min() >= SPEC.boundary_mm + SHAFT_SLACK_MM - 0.02
        assert np.all(np.abs(traj.derivative(1).vector_values(ts)) <= robot.qdot_max[:, None] * 1.001)


def test_insertion_and_withdrawal_run_along_the_shaft_and_join_the_sweep(planned):
    scenario, robot, model, plan = planned
    for seg in plan.segments:
        q_in_end, q_sweep0 = seg.insert.value(seg.insert.end_time())[:, 0], seg.sweep.trajectory.value(0.0)[:, 0]
        assert np.allclose(q_in_end, q_sweep0, atol=1e-9)
        q_sweep1 = seg.sweep.trajectory.value(seg.sweep.trajectory.end_time())[:, 0]
        assert np.allclose(seg.withdraw.value(0.0)[:, 0], q_sweep1, atol=1e-9)
        for traj in (seg.insert, seg.withdraw):
            ts = np.linspace(0.0, traj.end_time(), 50)
            Q = traj.vector_values(ts).T
            # the shaft stays on the line through the trocar (its pivot lies behind it on that line)
            assert max(robot.rcm_error_mm(q, seg.p_WC) for q in Q) < 0.05
            # the withdrawal's end, the insertion's start: the tip outside the eye
        for q in (seg.insert.value(0.0)[:, 0], seg.withdraw.value(seg.withdraw.end_time())[:, 0]):
            assert model.signed_distance(robot.pose("T", q)[1][None])[0] < 0


def test_switches_visit_each_port_once_and_move_outside_the_eye(planned):
    scenario, robot, model, plan = planned
    order = [seg.port.name for seg in plan.segments]
    changes = sum(a != b for a, b in zip(order[:-1], order[1:]))
    assert changes == len(set(order)) - 1 == 1
    assert len(plan.switches) == len(plan.segments) - 1
    for sw, move in zip(plan.switches, plan.moves):
        assert sw.move_min_outside_mm > 0 and sw.duration_s > 0
        ts = np.linspace(0.0, move.end_time(), 100)
        tips = np.array([robot.pose("T", q)[1] for q in move.vector_values(ts).T])
        assert np.max(model.signed_distance(tips)) < 0  # the tip stays outside the retina


def test_depression_cells_are_reached_with_the_wall_indented(planned):
    scenario, robot, model, plan = planned
    band, dep = plan.band, plan.band.reason == "depression"
    if not dep.any():
        pytest.skip("no cell needs scleral depression on this band")
    T = band.target_W[dep] + DEPRESSION_MM * band.normal_W[dep]
    ok = np.zeros(len(T), dtype=bool)
    for p in plan.ports:
        ok |= cell_reasons(robot, scenario, T, band.normal_W[dep], SPEC, p_EC=scenario.p_EC_of(p.name))[0] == "ok"
    assert ok.all()


def test_regions_wrap_round_the_azimuth():
    m = np.zeros((3, 10), dtype=bool)
    m[0, [0, 1, 9]] = True  # one region across the seam
    m[2, 4:6] = True
    parts = regions(m)
    assert [int(p.sum()) for p in parts] == [3, 2]
    assert np.array_equal(parts[0] | parts[1], m)


def test_a_cell_keeps_the_reason_of_the_port_that_got_furthest():
    r = combined_reason([np.array(["lens", "ok", "port", "lens"], dtype=object),
                         np.array(["reach", "lens", "port", "shaft"], dtype=object)])
    assert list(r) == ["reach", "ok", "port", "shaft"]
