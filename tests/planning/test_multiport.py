"""Multi-port planning: every swept cell from a port that reaches it, the sweeps through
their own trocar clear of the boundary, switches outside the eye, regions, reasons."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models import Ellipsoid
from planning import SurgeryScenario
from planning.multiport import DEPRESSION_MM, combined_reason, plan_ports, regions
from planning.peripheral import cell_reach
from planning.peripheral import SHAFT_SLACK_MM, BandSpec, cell_reasons, lens_clearances_mm, shaft_clearances_mm
from planning.port_moves import JOINT_MARGIN_RAD
from planning.ports import standard_ports
from planning.robot import Robot
from planning.scenario import EYE_WALL_MM, LENS_CLEARANCE_MM, PORTS_EYE_POSE

SPEC = BandSpec(z_min_E=0.0, z_max_E=2.0)
# the band's anterior half: cells next to the ports (the shaft crosses the wall right behind
# the cutter) and far, deep cells where the wrist reaches its limit on the way out
ANTERIOR = BandSpec(z_min_E=3.0, z_max_E=5.0)


@pytest.fixture(scope="module")
def layout():
    ports = standard_ports("right")
    scenario = SurgeryScenario(eye_pose=PORTS_EYE_POSE, ports=ports, p_EC=None)
    robot = Robot(scenario)
    eye = scenario.eye
    model = Ellipsoid(eye.pose.p_WE, eye.radii, eye.pose.R_WE)  # the true retina as the fitted model
    return scenario, robot, model, ports


@pytest.fixture(scope="module")
def anterior(layout):
    scenario, robot, model, ports = layout
    return plan_ports(robot, scenario, model, ports[:2], ANTERIOR)


@pytest.fixture(scope="module", params=["equatorial", "anterior"])
def planned(layout, request):
    scenario, robot, model, ports = layout
    plan = request.getfixturevalue("anterior") if request.param == "anterior" else plan_ports(robot, scenario, model,
                                                                                             ports[:2], SPEC)
    return scenario, robot, model, plan


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
        # the shaft keeps the cells' lens clearance on the way between them too (the filter's lens
        # margin, 0.3 mm, lies below it); 200 samples are coarser than the planner's check: 0.05 mm
        tips = np.array([robot.pose("T", q)[1] for q in Q])
        assert lens_clearances_mm(scenario.lens_W, seg.p_WC, tips).min() >= LENS_CLEARANCE_MM - 0.05


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
        for traj in (seg.insert, seg.withdraw):  # every joint the filter's margin inside its range, every 5 ms
            ts = np.append(np.arange(0.0, traj.end_time(), 0.005), traj.end_time())
            assert np.degrees(robot.joint_margin_rad(traj.vector_values(ts).T).min()) >= np.degrees(JOINT_MARGIN_RAD) - 1e-6


def test_every_cell_a_port_reaches_is_swept(planned):
    """On the true retina every cell that some port reaches (lens, port angle, arm, shaft at
    the cell) is swept: cells next to a port (no watched shaft point that deep) and the far,
    deep cells whose own shaft line the wrist cannot take out of the eye (the pass leaves
    through a door cell) included."""
    scenario, robot, model, plan = planned
    reached = np.any([r == "ok" for r in plan.reasons_by_port.values()], axis=0)
    assert reached.sum() > 0.9 * reached.size
    assert np.all(plan.port_of[reached] >= 0)


def test_a_cell_next_to_a_port_goes_to_the_other_port_when_it_reaches_it(layout, anterior):
    """Within a few mm of a trocar no shaft point the filter watches is that deep (clearance
    +inf); the shaft crosses the wall right behind the cutter there, so the other port, whose
    shaft reaches the cell across the eye, takes it when it can."""
    scenario, robot, model, ports = layout
    T, N = anterior.band.target_W.reshape(-1, 3), anterior.band.normal_W.reshape(-1, 3)
    reach = [cell_reach(robot, scenario, T, N, ANTERIOR, scenario.p_EC_of(p.name), model) for p in ports[:2]]
    port_of = anterior.port_of.reshape(-1)
    checked = 0
    for k in range(2):
        shallow = (reach[k][0] == "ok") & np.isposinf(reach[k][2])
        both = shallow & (reach[1 - k][0] == "ok")
        checked += int(both.sum())
        assert np.all(port_of[both] == 1 - k)
        assert np.all(port_of[shallow & ~both] == k)  # its own port only: still swept
    assert checked > 0  # the anterior band has such cells


def test_switches_visit_each_port_once_and_move_outside_the_eye(planned):
    scenario, robot, model, plan = planned
    order = [seg.port.name for seg in plan.segments]
    changes = sum(a != b for a, b in zip(order[:-1], order[1:]))
    assert changes == len(set(order)) - 1 == 1
    assert len(plan.switches) == len(plan.segments) - 1
    for sw, move in zip(plan.switches, plan.moves):
        assert sw.move_min_outside_mm >= EYE_WALL_MM and sw.duration_s > 0
        ts = np.linspace(0.0, move.end_time(), 100)
        tips = np.array([robot.pose("T", q)[1] for q in move.vector_values(ts).T])
        assert np.max(model.signed_distance(tips)) < -0.9 * EYE_WALL_MM  # the tip stays outside the eye wall
        ts = np.append(np.arange(0.0, move.end_time(), 0.005), move.end_time())
        assert robot.joint_margin_rad(move.vector_values(ts).T).min() >= JOINT_MARGIN_RAD - 1e-9


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


def test_cells_too_few_for_a_pass_are_reported_declined_not_as_geometry(layout, monkeypatch):
    """With every re-entry declined (MIN_PASS_CELLS above the band's size), each cell some
    port reaches but no pass sweeps is "declined", never a geometric reason."""
    import planning.multiport as multiport

    scenario, robot, model, ports = layout
    monkeypatch.setattr(multiport, "MIN_PASS_CELLS", 10**6)
    plan = plan_ports(robot, scenario, model, ports[:2], ANTERIOR)
    reached = np.any([r == "ok" for r in plan.reasons_by_port.values()], axis=0)
    left = reached & (plan.port_of < 0)
    assert left.sum() > 0  # one pass per port cannot sweep the anterior band (test above: re-entries and doors)
    assert np.all(plan.band.reason[left] == "declined")
    assert set(np.unique(plan.band.reason)) <= {"ok", *multiport.UNREACHABLE}


def test_a_move_whose_spline_swings_past_a_joint_limit_is_not_taken(setup):
    """A C2 cubic through waypoints that keep their limits can swing past one between them
    (here J6 through 150, 179 and 179.9 deg, back to 150: past 180 deg); such a candidate
    move is skipped, and the direct move between two postures with the margin keeps it."""
    from pydrake.trajectories import PiecewisePolynomial

    from planning.port_moves import _leaves_limits

    _, robot, q = setup
    Q = np.repeat(q[None], 4, axis=0)
    Q[:, 5] = np.radians([150.0, 179.0, 179.9, 150.0])
    swing = PiecewisePolynomial.CubicWithContinuousSecondDerivatives([0.0, 0.3, 0.6, 1.5], Q.T, np.zeros(6), np.zeros(6))
    ts = np.linspace(0.0, 1.5, 3001)
    assert np.degrees(swing.vector_values(ts)[5].max()) > 180.0  # the premise: the spline leaves the range
    assert _leaves_limits(robot, swing)
    direct = PiecewisePolynomial.CubicWithContinuousSecondDerivatives([0.0, 1.0], Q[[0, 1]].T, np.zeros(6), np.zeros(6))
    assert _leaves_limits(robot, direct)  # 179 deg: within the 2 deg margin of J6's end
    Q[1, 5] = np.pi - 1.01 * JOINT_MARGIN_RAD
    direct = PiecewisePolynomial.CubicWithContinuousSecondDerivatives([0.0, 1.0], Q[[0, 1]].T, np.zeros(6), np.zeros(6))
    assert not _leaves_limits(robot, direct)


@given(st.lists(st.floats(0.05, 2.0), min_size=1, max_size=6), st.integers(0, 2**31 - 1))
@settings(max_examples=30)
def test_the_withdrawal_is_its_planned_line_run_backwards_exactly(durations, seed):
    """The withdrawal is planned as an insertion and run backwards: the same curve (a cubic
    segment is its ends' values and velocities), not a new curve through its knots."""
    from pydrake.trajectories import PiecewisePolynomial

    from planning.multiport import _reversed

    rng = np.random.default_rng(seed)
    t = np.concatenate([[0.0], np.cumsum(durations)])
    line = PiecewisePolynomial.CubicHermite(t, rng.normal(size=(6, len(t))), rng.normal(size=(6, len(t))))
    back = _reversed(line)
    ts = np.linspace(0.0, t[-1], 97)
    assert back.start_time() == 0.0 and back.end_time() == pytest.approx(t[-1], abs=1e-12)
    assert np.allclose(back.vector_values(ts), line.vector_values(t[-1] - ts), atol=1e-9)


def test_a_pass_whose_ends_cannot_leave_far_enough_leaves_through_a_door_that_can(layout, monkeypatch):
    """Where no cell's shaft line takes the tip EXIT_MM out (the wrist's margin on the way)
    and the end cells' lines not even MIN_EXIT_MM, a pass enters and leaves through the
    nearest cell whose line takes it MIN_EXIT_MM out: here the middle ring's."""
    import planning.multiport as multiport

    scenario, robot, model, ports = layout
    real = multiport._end_line

    def line(robot_, band, cell, q, p_WC, out_mm):
        if out_mm > multiport.MIN_EXIT_MM or cell[0] != 1:  # only the middle ring, only MIN_EXIT_MM out
            return None
        return real(robot_, band, cell, q, p_WC, out_mm)

    monkeypatch.setattr(multiport, "_end_line", line)
    plan = plan_ports(robot, scenario, model, ports[:2], SPEC)
    assert len(plan.segments) >= 2 and (plan.port_of >= 0).sum() > 0.5 * plan.port_of.size
    for seg in plan.segments:
        assert seg.sweep.cells[0][0] == 1 and seg.sweep.cells[-1][0] == 1  # doors in the middle ring
        for q in (seg.insert.value(0.0)[:, 0], seg.withdraw.value(seg.withdraw.end_time())[:, 0]):
            p_T = robot.pose("T", q)[1]
            assert model.signed_distance(p_T[None])[0] < 0  # the tip outside the eye


def test_a_band_no_port_can_sweep_is_refused_with_every_cells_reason(layout):
    """A model whose uncertainty puts the boundary past every shaving target (u = 2 mm, k = 1,
    targets 1 mm deep): no cell is swept, and the refusal counts the cells and their reasons."""
    from models.adaptive.model_field import ModelField
    from planning.field_model import FieldModel
    from planning.ik import IKFailure

    scenario, robot, model, ports = layout
    with pytest.raises(IKFailure) as err:
        plan_ports(robot, scenario, FieldModel(ModelField(model, 2.0), 1.0, "sphere"), ports[:2], SPEC)
    msg = str(err.value)
    n = int(msg.split("(")[1].split(" cells")[0])
    assert n > 0 and msg.endswith(f"({n} cells: {n} uncertain)")
