"""The closed loop in Drake: the filter keeps the instrument off the TRUE retina while the
RCM holds, tracks the command in free space, fails safe inside the loop, and its log
replays bit for bit."""
from __future__ import annotations

import copy

import numpy as np
import pytest

from eval.experiments.boundary import VIOLATION_MM, adversarial_starts, run_campaign
from eval.closed_loop import ClosedLoop, LoopConfig
from eval.experiments.command_sources import TipPathCommand, VelocityReplayCommand
from eval.log.writer import RunLogger
from eval.log.replay import replay
from models import AdaptiveEyeModel, Ellipsoid
from models.adaptive.coverage import DirectionCoverage
from models.adaptive.transition import PredictiveCriteria
from models.local.grid import LocalRetinaModel
from planning import SurgeryScenario, start_posture
from safety import FilterConfig

RCM_TOL_MM = 0.020  # RCM drift of 1 kHz Euler steps of the joint velocities, up to 20 mm/s


def model_from_spiral_beams(scenario: SurgeryScenario, seed: int = 0, local: bool = False,
                            pitch_mm: float = 1.5, revolutions: float = 6.0):
    """(AdaptiveEyeModel, DirectionCoverage) from the retina points the fiber would see
    along the spiral (`pitch_mm`, `revolutions`; beams from the trocar through the spiral
    points, 20 um noise), without the robot; with `local`, the model has its local part
    (models.local)."""
    P_E = scenario.spiral_E(pitch_mm=pitch_mm, revolutions=revolutions, spacing_mm=0.05)
    P = scenario.eye_pose.to_W(P_E)
    U = P - scenario.p_WC
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    d = scenario.eye.ray_cast(P, U)
    X = P + (d + np.random.default_rng(seed).normal(0.0, 0.02, len(d)))[:, None] * U
    model = AdaptiveEyeModel(criteria=PredictiveCriteria(),
                             local=LocalRetinaModel(scenario.eye_pose.p_WE) if local else None)
    coverage = DirectionCoverage(scenario.eye_pose.p_WE)
    for k in range(0, len(X), 10):
        model.update(X[k:k + 10])
    coverage.add(X)
    return model, coverage


@pytest.fixture(scope="module")
def emmetropic():
    scenario = SurgeryScenario()
    model, coverage = model_from_spiral_beams(scenario, local=True)
    assert model.kind == "ellipsoid"
    return ClosedLoop(scenario), State(model, coverage)


@pytest.mark.parametrize("params", [{}, {"height_mm": 3.5, "angle_deg": 25.0}])
def test_the_local_models_sigma_covers_a_detachment_on_the_unsafe_side(params):
    """The population's detachment (2 mm high, 10 mm across, 40 deg off the pole; and one
    3.5 mm high at 25 deg) scanned by the spiral: between its rings and past its edge the
    flank rises away from the global ellipsoid by up to 1 mm (3 mm). The barrier keeps d_safe + 3 sigma from the model's retina, so
    wherever the model puts the retina beyond the true one, 3 sigma must cover the excess
    (models.metrics.field_report's unsafe side); the global quadric under it stays an eye's."""
    from models.metrics import field_report

    scenario = SurgeryScenario(eye_name="detached", eye_params=params)
    model, coverage = model_from_spiral_beams(scenario, local=True)
    field = model.local.field()
    r = field_report(field, scenario.eye, coverage.view().angle_from_data_rad)
    assert r["sigma3_unsafe_fraction"] == 0.0 and r["sigma3_worst_excess_um"] < 0.0
    assert r["sigma3_coverage"] >= 0.99  # the 3-sigma coverage target, both sides
    assert r["mae_um"] <= 150.0  # and honest without being vague: the MAE target


class State:
    """The model and its coverage; `kw()` fresh copies for one run."""

    def __init__(self, model, coverage):
        self.model, self.coverage = model, coverage

    def kw(self) -> dict:
        return {"model": copy.deepcopy(self.model), "coverage": copy.deepcopy(self.coverage)}


def deep_start(loop):
    """A posture with the tip 5 mm behind the eye centre, far from the retina."""
    p = loop.scenario.eye_pose.to_W(np.array([[1.0, 1.0, -5.0]]))[0]
    return start_posture(loop.robot, p, loop.scenario.p_WC)


def test_adversarial_scenarios_keep_the_true_clearance_on_a_regular_eye(emmetropic):
    loop, model = emmetropic
    campaign = run_campaign(loop, model.model, model.coverage, 4, seed=3, duration_s=0.5)
    s = campaign.summary()
    assert s["violations"] == 0 and s["contacts"] == 0 and s["lens_violations"] == 0
    assert s["min_true_clearance_mm"] >= VIOLATION_MM
    assert s["failsafe_stops"] == 0
    assert s["max_rcm_error_um"] <= 1e3 * RCM_TOL_MM
    # the adversary really attacks: the boundary is reached (within 0.3 mm of the 0.5 mm boundary)
    assert s["min_true_clearance_mm"] <= 0.8 and s["intervention_fraction"] > 0.05
    # and the barrier's premise held: no monitored point's true clearance fell under the bound it assumed
    assert s["bound_over_truth_runs"] == 0 and s["max_bound_excess_mm"] < 0.0


def test_a_model_that_is_not_the_eye_shows_as_bounds_over_the_truth(emmetropic):
    """The emmetropic eye's local model against a hyperopic eye (shorter: its retina nearer than
    the model's, with the model's sigma tens of um): the bounds the barrier assumed lie over
    the true clearance, and the run's largest excess is what every step's bounds and points give."""
    _, model = emmetropic
    loop = ClosedLoop(SurgeryScenario(eye_name="hyperopic"), LoopConfig(local_model=True))
    eye = loop.scenario.eye
    path_W = loop.scenario.eye_pose.to_W(np.array([[0.0, 0.0, -9.0], [0.0, 0.0, -11.5]]))  # towards the pole
    q0 = start_posture(loop.robot, path_W[0], loop.scenario.p_WC)
    run = loop.run(TipPathCommand(np.array([0.0, 1.0]), path_W), q0, 1.0, **model.kw())
    steps = loop.filter.record.steps
    every = [np.where(np.isfinite(st.bounds_mm), st.bounds_mm - eye.signed_distance(st.points_W), -np.inf)
             for st in steps]
    k = int(np.argmax([e.max() for e in every]))
    assert run.bound_excess_mm == every[k].max() > 0.0 and run.bound_excess_step == k


def test_free_space_command_is_tracked_within_1_percent(emmetropic):
    loop, model = emmetropic
    v = np.array([2.0, -1.0, 1.5])  # mm/s, 0.3 s: the tip moves 0.8 mm from a point 5 mm deep
    run = loop.run(VelocityReplayCommand([0.0], [v]), deep_start(loop), 0.3, **model.kw())
    moving = np.linalg.norm(run.v_cmd, axis=1) > 0
    assert moving.sum() > 250 and run.ok.all()
    assert not run.intervened[moving].any()
    err = np.linalg.norm(run.v_tip[moving] - run.v_cmd[moving], axis=1) / np.linalg.norm(v)
    assert err.max() < 0.01
    assert np.nanmax(run.rcm_error_mm) <= RCM_TOL_MM


def test_a_tip_path_is_followed(emmetropic):
    loop, model = emmetropic
    q0 = deep_start(loop)
    p0 = loop.robot.pose("T", q0)[1]
    t = np.array([0.0, 0.3])
    path = TipPathCommand(t, np.vstack([p0, p0 + [1.5, 0.0, 0.0]]))
    run = loop.run(path, q0, 0.4, **model.kw())
    p_end = loop.robot.pose("T", run.q[-1])[1]
    assert np.linalg.norm(p_end - (p0 + [1.5, 0.0, 0.0])) < 0.05  # the position feedback holds the tip at the path's end (0.1 s after it)
    # the command source's and the model system's own time is part of the run's, and counted afresh per run
    assert 0.0 < run.command_wall_s and 0.0 < run.model_wall_s and run.command_wall_s + run.model_wall_s < run.wall_s


def test_the_command_is_made_for_the_joint_angles_the_filter_filters(emmetropic):
    """The command source runs inside the filter's step: it is called once per step, in
    time order, with that step's time, joint angles and tip position, and the command
    the step records is the one it returned (no step of latency)."""
    loop, model = emmetropic
    calls = []

    def source(t_s, p_WT, q):
        v = np.array([1.0 + t_s, 0.0, -0.5])  # a different command each step
        calls.append((t_s, np.array(p_WT), np.array(q), v))
        return v, 0.0

    q0 = deep_start(loop)
    run = loop.run(source, q0, 0.05, **model.kw())
    assert len(calls) == len(run.t) == round((0.05 - run.t[0]) * 1e3) > 30  # 1 kHz from the first packet on
    assert not run.logged
    for (t_s, p_WT, q, v), t, q_run, v_run in zip(calls, run.t, run.q, run.v_cmd):
        assert t_s == t
        np.testing.assert_array_equal(q, q_run)
        np.testing.assert_allclose(p_WT, loop.robot.pose("T", q)[1], atol=1e-12)  # mm
        np.testing.assert_array_equal(v, v_run)


def test_nan_commands_stop_the_robot_where_it_is(emmetropic):
    loop, model = emmetropic
    V = np.array([[2.0, 0.0, 0.0], [np.nan, 0.0, 0.0], [2.0, 0.0, 0.0]])
    run = loop.run(VelocityReplayCommand([0.0, 0.05, 0.15], V), deep_start(loop), 0.2, **model.kw())
    bad = ~run.ok
    assert 90 <= bad.sum() <= 101
    assert all("non-finite v_cmd_W" in r for r, b in zip(run.reasons, bad) if b)
    assert np.all(run.qdot[bad] == 0.0)
    k = np.flatnonzero(bad)
    # zero-order hold + integrator: the joints stop one step after the fault is seen
    assert np.abs(np.diff(run.q[k[1]:k[-1] + 1], axis=0)).max() == 0.0
    assert run.failsafe_stops == 1


def test_a_stale_sensor_keeps_the_robot_still():
    """A packet's newest sample is at least 0.5 ms old at a control step; with a 0.3 ms age
    limit every step is a fault."""
    scenario = SurgeryScenario()
    loop = ClosedLoop(scenario, LoopConfig(filter=FilterConfig(max_sensor_age_s=3e-4)))
    q0 = deep_start(loop)
    run = loop.run(VelocityReplayCommand([0.0], [[3.0, 0.0, 0.0]]), q0, 0.05)
    assert not run.ok.any() and all(r.startswith("stale sensor") for r in run.reasons)
    assert np.array_equal(run.q[-1], q0)


def test_the_model_receives_every_sensor_packet_exactly_once():
    """The 200 samples of 0-99.5 ms at 2 kHz, in packets of 5 or 10 ms: the sensor latches
    the 1 kHz joint angles at whole ms, so it processes each packet a quarter sample after
    the latch at the next whole ms (1.25 samples after the packet's last sample: the last
    packet at 100.125 ms), and the model reads it a quarter sample later (100.25 ms): a run
    of 101 ms gets all of them (the next packet ends at 104.5 ms at the earliest), none twice
    (the model skips samples it has seen). Not on the latch times themselves: a packet event
    on the sample times lost one in 20 to Drake's rounding of the two periodic series."""
    scenario = SurgeryScenario()
    loop = ClosedLoop(scenario)
    loop.run(VelocityReplayCommand([0.0], [[2.0, 0.0, 0.0]]), deep_start(loop), 0.101)
    assert loop.model.n_samples == 200 and loop.model._last_t == 199 * 5e-4


def test_control_steps_fall_on_the_integrators_times_from_the_first_packet_on():
    """The filter's steps are the integrator's instants k x 1 ms, bit for bit, from the
    first packet's arrival (11 ms: 20 samples at 2 kHz, processed and modelled by 10.25
    ms) on: one simulator step per control period plus the sensor's and the model's
    100 Hz events (a step series of its own rounded apart from the integrator's in one
    step in four, each an extra simulator step)."""
    scenario = SurgeryScenario()
    loop = ClosedLoop(scenario)
    run = loop.run(VelocityReplayCommand([0.0], [[2.0, 0.0, 0.0]]), deep_start(loop), 0.1)
    assert run.t.tolist() == (np.arange(11, 100) * 1e-3).tolist()
    assert loop.simulator.get_num_steps_taken() <= 100 + 2 * 10 + 2


def test_the_model_system_takes_the_valid_points_of_each_packets_new_samples(emmetropic):
    """Two packets from the sensor (floaters among them, and beams too long for a
    shortened engine: invalid), the second repeating the last 5 sample times of the
    first: the model system counts 10 + 5 new samples, keeps the errors (extracted -
    true, mm) of the valid ones exactly and gives the model exactly the points a model fed
    those valid points directly takes."""
    from pydrake.common.value import AbstractValue

    from planning.iioct import IioctSensor

    loop, _ = emmetropic
    q = deep_start(loop)
    Q = q + np.linspace(0.0, 0.03, 15)[:, None] * np.array([1.0, -0.5, 0.3, 0.0, 0.2, 0.0])
    T = np.arange(15) * 5e-4
    sensor = IioctSensor(loop.robot, mode="distance", floater_rate=0.3, seed=3)
    sensor.max_distance_mm = 5.78  # the beams along Q: 5.6-5.8 mm
    a, b = sensor.packet(Q[:10], Q[:10], T[:10]), sensor.packet(Q[5:], Q[5:], T[5:])
    new_b = b.take(np.arange(5, 10))
    assert not a.valid.all() and new_b.valid.any()
    system, reference = loop.model, AdaptiveEyeModel()
    system.reset(AdaptiveEyeModel(), DirectionCoverage(loop.scenario.eye_pose.p_WE))
    context = system.CreateDefaultContext()
    for packet in (a, b):
        system.get_input_port(0).FixValue(context, AbstractValue.Make(packet))
        system._absorb(context, context.get_mutable_state())
    for packet in (a, new_b):
        reference.update(packet.p_W[packet.valid])
    assert system.n_samples == 15 and system.n_invalid == 15 - a.valid.sum() - new_b.valid.sum()
    errors = [p.distance_mm[p.valid] - p.true_distance_mm[p.valid] for p in (a, new_b)]
    assert system.errors_mm == np.concatenate(errors).tolist()
    assert system.model.n_received == reference.n_received and system.model.n_points == reference.n_points
    np.testing.assert_array_equal(system.model.last_accepted, reference.last_accepted)
    assert context.get_abstract_state(0).get_value().t_s == T[-1]


def test_the_prior_bounds_the_motion_until_the_model_is_trusted():
    scenario = SurgeryScenario()
    loop = ClosedLoop(scenario)
    run = loop.run(VelocityReplayCommand([0.0], [[0.0, 0.0, 0.0]]), deep_start(loop), 0.05)
    assert set(run.kind) == {"prior"}  # a still beam gives a scan range of 0: never trusted


def test_adversarial_starts_are_inside_and_reachable(emmetropic):
    loop, model = emmetropic
    starts = adversarial_starts(loop, model.model.shape, 5, np.random.default_rng(0))
    for q in starts:
        p = loop.robot.pose("T", q)[1]
        assert 1.5 - 0.3 <= loop.scenario.eye.signed_distance(p[None])[0] <= 4.0 + 0.5
        assert loop.robot.rcm_error_mm(q, loop.scenario.p_WC) < 1e-3


def test_a_closed_loop_log_replays_bit_for_bit(emmetropic, tmp_path):
    loop, model = emmetropic
    q0 = deep_start(loop)
    with RunLogger(tmp_path / "loop.mcap", loop.config.filter) as log:
        run = loop.run(VelocityReplayCommand([0.0], [[5.0, 0.0, -3.0]]), q0, 0.1, **model.kw(), logger=log)
    assert run.logged  # its realtime factor holds the log's writes: campaigns report it apart
    result = replay(tmp_path / "loop.mcap")
    assert result.ok and result.steps >= 85 and result.max_abs_diff == 0.0  # 1 kHz from the first packet (11 ms) to 0.1 s


def test_a_log_of_a_robot_with_its_own_dynamics_replays_bit_for_bit(emmetropic, tmp_path):
    """Delay, lag and acceleration limit (the fault classes' values): each step's record holds
    the actuator's pending displacements, and replay rebuilds the actuator-aware barriers,
    the RCM rows and the planned stops the run made from them."""
    from safety.actuator import ActuatorModel

    _, model = emmetropic
    actuator = ActuatorModel(delay_s=0.005, lag_s=0.02, accel_limit_rad_s2=float(np.radians(1000.0)))
    loop = ClosedLoop(SurgeryScenario(), LoopConfig(actuator=actuator))
    q0 = deep_start(loop)
    with RunLogger(tmp_path / "robot.mcap", loop.config.filter) as log:  # 20 mm/s towards the retina and along it
        run = loop.run(VelocityReplayCommand([0.0, 0.25], [[0.0, 0.0, 20.0], [15.0, 10.0, 10.0]]), q0, 0.5,
                       **model.kw(), logger=log)
    stops = {r for ok, r in zip(run.ok, run.reasons) if not ok}
    assert stops and all(r.startswith("actuator cannot") for r in stops)  # the run made planned stops
    result = replay(tmp_path / "robot.mcap")
    assert result.ok and result.steps >= 480 and result.max_abs_diff <= 1e-9


def test_segments_through_two_trocars_pivot_about_each_and_replay_bit_for_bit(emmetropic, tmp_path):
    """run_segments: the filter's RCM follows each segment's trocar (the RCM error stays at
    the IK's level about the active trocar), the log gets a setup per trocar, and replay
    rebuilds each step's kinematics on its own trocar."""
    from planning.ports import Port

    loop, model = emmetropic
    scenario = loop.scenario
    other = SurgeryScenario(ports=(Port("other", "working", 2.0, 4.0),)).p_WC_of("other")  # 4 mm from the trocar
    p = scenario.eye_pose.to_W(np.array([[1.0, 1.0, -5.0]]))[0]
    q_a, q_b = deep_start(loop), start_posture(loop.robot, p, other)
    hold = VelocityReplayCommand([0.0], [[2.0, 0.0, -1.0]])
    with RunLogger(tmp_path / "two.mcap", loop.config.filter) as log:
        run = loop.run_segments([(scenario.p_WC, hold, q_a, 0.05), (other, hold, q_b, 0.05)], **model.kw(), logger=log)
    t_b = 0.05
    a, b = run.t < t_b - 1e-9, run.t > t_b - 1e-9  # the second segment starts at rest: no stale command
    assert max(loop.robot.rcm_error_mm(q, scenario.p_WC) for q in run.q[a]) < RCM_TOL_MM
    assert max(loop.robot.rcm_error_mm(q, other) for q in run.q[b]) < RCM_TOL_MM
    assert np.all(run.ok)
    # Drake is timed on every 25th step's state, the filter replayed on those of the last trocar (its RCM)
    every = loop.config.drake_diffik_every
    steps = np.arange(len(run.t))
    assert len(run.drake_diffik_us) == np.sum(steps % every == 0)
    assert len(run.filter_replay_us) == np.sum((steps % every == 0) & b) > 0
    assert np.all(np.isfinite(run.filter_replay_us)) and np.all(run.filter_replay_us > 0)
    assert not loop.filter.stack.active.any()  # the replay's active set is forgotten
    result = replay(tmp_path / "two.mcap")
    # the second trocar is logged in E and placed back in W: a rounding of 1e-14 mm
    assert result.ok and result.max_abs_diff <= 1e-12 and result.steps == len(run.t)
    loop.filter.set_trocar(scenario.p_WC)


def test_bad_loop_arguments_are_refused(emmetropic):
    loop, model = emmetropic
    cmd = VelocityReplayCommand([0.0], [[0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="q0"):
        loop.run(cmd, np.full(6, np.nan), 0.1)
    with pytest.raises(ValueError, match="duration_s"):
        loop.run(cmd, deep_start(loop), -1.0)
    with pytest.raises(ValueError, match="sensor_mode"):
        LoopConfig(sensor_mode="camera")
    with pytest.raises(ValueError, match="sensor_rate_hz must be an integer multiple"):
        LoopConfig(sensor_rate_hz=1500.0)
    with pytest.raises(ValueError, match="sensor_packet must be an int >= 1 and a multiple"):
        LoopConfig(sensor_packet=5)


def test_adversarial_starts_are_inside_the_true_retina_where_the_model_bulges_past_it():
    """A model 3 mm too large (like the pointed eye's ellipsoid at its periphery) must not
    put a start in the eye wall: the nearer of model and truth sets the depth."""
    scenario = SurgeryScenario()
    loop = ClosedLoop(scenario)
    e = scenario.eye.ellipsoid
    too_big = Ellipsoid(e.center, e.radii + 3.0, e.rotation)
    for q in adversarial_starts(loop, too_big, 5, np.random.default_rng(1)):
        p = loop.robot.pose("T", q)[1]
        assert 1.5 - 0.3 <= scenario.eye.signed_distance(p[None])[0] <= 4.0 + 0.5


def test_an_ascan_mode_run_logs_a_scans_at_20_hz(emmetropic, tmp_path):
    """The log holds A-scans: in "ascan" mode one in ASCAN_LOG_EVERY (20 Hz of the
    2 kHz stream), each the engine's full length, beside every distance."""
    from eval.systems.model import ASCAN_LOG_EVERY
    from eval.log.writer import read_log

    loop, state = emmetropic
    ascan_loop = ClosedLoop(loop.scenario, LoopConfig(sensor_mode="ascan"))
    with RunLogger(tmp_path / "a.mcap", ascan_loop.config.filter) as log:
        ascan_loop.run(VelocityReplayCommand([0.0], [[2.0, 0.0, 0.0]]), deep_start(ascan_loop), 0.2, logger=log, **state.kw())
    messages = read_log(tmp_path / "a.mcap").messages
    scans, distances = messages["/oct/ascan"], messages["/oct/distance"]
    assert len(distances) >= 380  # 2 kHz for 0.2 s, the last packet (20 samples) may be pending
    assert len(scans) == -(-len(distances) // ASCAN_LOG_EVERY)
    assert all(m["n_samples"] == ascan_loop.sensor.engine.n_samples for _, m in scans)


def test_an_ellipsoid_that_is_no_eye_gives_way_to_the_sphere_fit():
    """On the pointed eye's paper spiral the ellipsoid ends at about 129 x 27 x 27 mm (its
    posterior paraboloid), outside an eye's 8-16 mm: the filter reads the sphere fit
    (radius 10.6 mm), with the sphere's residual; with no eye-sized fit it keeps the prior."""
    from eval.closed_loop import snapshot_of
    from models.eyes import make_eye
    from models.scan.paper_scan import paper_scan

    model = AdaptiveEyeModel()
    for p in paper_scan(make_eye("pointed"), seed=0).points:
        model.update(p)
    assert model.kind == "ellipsoid" and model.ellipsoid.radii.max() > 16.0
    coverage = DirectionCoverage(np.zeros(3))
    snap = snapshot_of(model, coverage, 1.0, 200, 5.0, (8.0, 16.0))
    assert snap.kind == "sphere" and 8.0 <= snap.shape.radius <= 16.0
    assert snap.shape.radius == model.sphere.radius and np.array_equal(snap.shape.center, model.sphere.center)
    assert snap.residual_mm == model.history[-1].sf_residual_mm
    assert snapshot_of(model, coverage, 1.0, 200, 5.0, (8.0, 10.0)).kind == "prior"


def test_the_snapshot_holds_the_models_own_shapes_once_trusted():
    """Along the paper spiral in packets of 10: below the trust limits (200 points, 5 mm
    of scan range) the snapshot is the prior's, and the model's sphere is not made for it;
    past them it holds the model's current shape itself (one per update), that phase's
    residual and the coverage's view for the shape; a second snapshot before the next
    update holds the same objects."""
    from eval.closed_loop import snapshot_of
    from models.eyes import make_eye
    from models.scan.paper_scan import paper_scan

    points = paper_scan(make_eye("emmetropic"), seed=0).points
    model, coverage = AdaptiveEyeModel(), DirectionCoverage(np.zeros(3))
    kinds = []
    for k in range(0, len(points), 10):
        model.update(points[k:k + 10])
        coverage.add(model.last_accepted)
        snap = snapshot_of(model, coverage, 1.0, 200, 5.0, (8.0, 16.0))
        assert snap.n_points == model.n_points
        if model.n_points < 200 or model.scan_range_mm < 5.0:
            assert snap.kind == "prior" and snap.shape is None and model._sf._sphere is None
            continue
        kinds.append(snap.kind)
        assert snap.kind == model.kind and snap.shape is model.shape
        last = model.history[-1]
        assert snap.residual_mm == (last.ef_residual_mm if snap.kind == "ellipsoid" else last.sf_residual_mm)
        assert snap.coverage is coverage.view(model.shape)
        again = snapshot_of(model, coverage, 2.0, 200, 5.0, (8.0, 16.0))
        assert again.shape is snap.shape and again.coverage is snap.coverage and again.t_s == 2.0
    assert kinds[0] == "sphere" and kinds[-1] == "ellipsoid"
