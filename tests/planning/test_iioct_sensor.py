"""The iiOCT sensor on the robot: true beam on the true eye, point from the reported
angles and the calibrated pose; distance mode = the full chain's statistics; the Drake
block with packets, time offset and bad joint states."""
from __future__ import annotations

import copy
import dataclasses
from unittest import mock

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.interpolate import RegularGridInterpolator
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, DiscreteTimeIntegrator

from pydrake.systems.framework import LeafSystem

from planning import Robot, SurgeryScenario, start_posture
from planning.iioct_sensor import (BAD_JOINT_STATE, DISTANCE_MODE_CONFIDENCE, IioctSensor, IioctSensorSystem,
                                   SensorPacket, _PacketProcessor, extractor_error_model, sensor_beams)


def test_the_beam_comes_from_the_true_sensor_and_the_point_from_the_calibrated_one(setup):
    scenario, robot, q = setup
    s = IioctSensor(robot, mode="distance", seed=1)
    sample = s.sample(q, q, 0.0)
    assert sample.valid and sample.reason == ""
    o_true, u_true = robot.beam(q, true=True)
    d_true = scenario.eye.ray_cast(o_true[None], u_true[None])[0]
    assert abs(sample.distance_mm - d_true) < 0.1  # extractor error at normal incidence: tens of um
    o, u = robot.beam(q)
    np.testing.assert_allclose(sample.p_W, o + sample.distance_mm * u, atol=1e-12)
    # the point misses the true hit by about the calibration error (20 um, 0.1 deg over ~8 mm: ~25 um)
    assert np.linalg.norm(sample.p_W - (o_true + d_true * u_true)) < 0.1


def test_a_wrong_calibration_shifts_the_points_as_predicted(setup):
    scenario, robot, q = setup
    offset = np.array([0.1, -0.05, 0.0])  # mm, in S
    a = IioctSensor(robot, mode="distance", seed=4).sample(q, q, 0.0)
    b = IioctSensor(robot, mode="distance", seed=4, X_S_Scal=(np.eye(3), offset)).sample(q, q, 0.0)
    R_WS, _ = robot.pose("S", q)
    np.testing.assert_allclose(b.p_W - a.p_W, R_WS @ offset, atol=1e-12)


def test_distance_mode_matches_the_full_chain_statistically(setup):
    """Same geometry, 150 samples each: bias within 10 um and SD within a factor 2 (the
    error model is tabulated from the extractor with 24 scans per cell); valid counts
    within 4 binomial SDs below the tabulated invalid fraction's expectation (at this
    beam, ~7.7 mm at ~19 deg: p_invalid ~7 %, 139 +- 3 valid)."""
    scenario, robot, q = setup
    n, stats = 150, {}
    for mode in ("ascan", "distance"):
        s = IioctSensor(robot, mode=mode, seed=7)
        d = np.array([x.distance_mm for x in s.samples([q] * n, [q] * n, np.arange(n) * 5e-4) if x.valid])
        stats[mode] = (np.median(d), np.std(d), len(d))
    assert abs(stats["ascan"][0] - stats["distance"][0]) < 0.010
    assert 0.5 < stats["distance"][1] / stats["ascan"][1] < 2.0
    p = extractor_error_model().interpolate(*s.true_geometry(np.array([q])))[0, 0]
    assert stats["ascan"][2] >= n * (1 - p) - 4 * np.sqrt(n * p * (1 - p))
    assert stats["distance"][2] >= n * (1 - p) - 4 * np.sqrt(n * p * (1 - p))


def test_the_error_model_is_tabulated_from_the_extractor():
    m = extractor_error_model()
    normal = [m.bias[i][0] for i in range(len(m.distances_mm))]
    assert max(abs(b) for b in normal) <= 0.005  # issue 5: |bias| <= 5 um at normal incidence
    assert max(m.sd[i][0] for i in range(len(m.distances_mm))) <= 0.020  # SD <= 20 um
    assert m.p_invalid[-1][-1] > 0.5  # 25 mm at 75 deg: mostly invalid


def test_encoder_noise_scatters_the_points(setup):
    scenario, robot, q = setup
    quiet = IioctSensor(robot, mode="distance", seed=2)
    noisy = IioctSensor(robot, mode="distance", seed=2, encoder_noise_rad=1e-4)
    P = [np.array([s.p_W for s in sensor.samples([q] * 100, [q] * 100, np.arange(100) * 5e-4)]) for sensor in (quiet, noisy)]
    # 1e-4 rad on joints 160-300 mm from the tip moves the point by tens of um laterally
    assert np.linalg.norm(np.nanstd(P[1], axis=0)) > 3 * np.linalg.norm(np.nanstd(P[0], axis=0))


def test_bad_joint_angles_give_an_invalid_sample_never_a_point(setup):
    scenario, robot, q = setup
    s = IioctSensor(robot, mode="distance")
    bad = s.sample(np.full(6, np.nan), q, 0.0)
    assert not bad.valid and bad.reason.startswith("bad_joint_state") and np.all(np.isnan(bad.p_W))
    with pytest.raises(ValueError, match="mode"):
        IioctSensor(robot, mode="video")
    with pytest.raises(ValueError, match="encoder_noise_rad"):
        IioctSensor(robot, encoder_noise_rad=-1.0)


def _moving_diagram(robot, q0, qdot, offset_s, input_rate_hz=None):
    """q(t) = q0 + t qdot, integrated at 2 kHz (or at input_rate_hz, which the block is
    told), into the sensor block; returns (simulator, sensor system)."""
    b = DiagramBuilder()
    src = b.AddSystem(ConstantVectorSource(qdot))
    integ = b.AddSystem(DiscreteTimeIntegrator(6, 1.0 / (input_rate_hz or 2000.0)))
    sensor = b.AddSystem(IioctSensorSystem(IioctSensor(robot, mode="distance", seed=0), 2000.0, offset_s, packet=10,
                                           input_rate_hz=input_rate_hz))
    b.Connect(src.get_output_port(), integ.get_input_port())
    b.Connect(integ.get_output_port(), sensor.GetInputPort("q"))
    d = b.Build()
    sim = Simulator(d)
    integ.set_integral_value(integ.GetMyMutableContextFromRoot(sim.get_mutable_context()), q0)
    return sim, sensor


def test_the_block_samples_at_2_khz_in_packets_and_the_time_offset_moves_the_points(setup):
    scenario, robot, q = setup
    qdot = np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0])  # rad/s
    out = {}
    for offset in (0.0, 0.002):
        sim, sensor = _moving_diagram(robot, q, qdot, offset)
        sim.AdvanceTo(0.0101)
        ctx = sensor.GetMyContextFromRoot(sim.get_context())
        packet = sensor.GetOutputPort("packet").Eval(ctx)
        m = sensor.GetOutputPort("measurement").Eval(ctx)
        assert packet.n_samples == 10 and np.allclose(np.diff(packet.t_s), 5e-4)
        assert m[3] == packet.t_s[-1] and m[1] == 1.0
        out[offset] = packet.sample(-1)
    # with the offset the beam is taken 2 ms earlier: the origin lags by |v_origin| x 2 ms
    o_then, _ = robot.beam(q + (out[0.0].t_s - 0.002) * qdot)
    np.testing.assert_allclose(out[0.002].beam_origin_W, o_then, atol=1e-9)
    lag = np.linalg.norm(out[0.002].beam_origin_W - out[0.0].beam_origin_W)
    v = np.linalg.norm(robot.jacobian("S", np.zeros(3), q) @ qdot)
    assert abs(lag - v * 0.002) < 0.05 * v * 0.002


def test_the_batched_draws_have_the_error_models_bias_sd_and_invalid_fraction():
    """20,000 draws at an off-grid cell point (6.3 mm, 30 deg): the invalid fraction, the
    mean error and the SD within 4 standard errors of the interpolated table values."""
    m = extractor_error_model()
    n, d0, a0 = 20_000, 6.3, np.radians(30.0)
    p, bias, sd = m.interpolate(np.array([d0]), np.array([a0]))[0]
    d, valid = m.draws(np.full(n, d0), np.full(n, a0), np.random.default_rng(3))
    assert abs((1.0 - valid.mean()) - p) < 4.0 * np.sqrt(max(p * (1.0 - p), 1.0 / n) / n)
    assert np.isnan(d[~valid]).all() and np.isfinite(d[valid]).all()
    err = d[valid] - d0
    assert abs(err.mean() - bias) < 4.0 * sd / np.sqrt(valid.sum())
    assert abs(err.std(ddof=1) / sd - 1.0) < 4.0 / np.sqrt(2.0 * (valid.sum() - 1))


def test_the_table_interpolation_is_bilinear_and_clamped():
    """At the grid nodes the table values; at a cell's centre the mean of its corners;
    outside the grid the value at its edge."""
    m = extractor_error_model()
    D, A = np.array(m.distances_mm), np.array(m.incidences_rad)
    tables = np.stack([m.p_invalid, m.bias, m.sd], axis=-1)
    dd, aa = np.meshgrid(D, A, indexing="ij")
    np.testing.assert_allclose(m.interpolate(dd.ravel(), aa.ravel()), tables.reshape(-1, 3), atol=1e-15)
    centre = m.interpolate(np.array([0.5 * (D[2] + D[3])]), np.array([0.5 * (A[1] + A[2])]))[0]
    np.testing.assert_allclose(centre, tables[2:4, 1:3].mean(axis=(0, 1)), atol=1e-15)
    outside = m.interpolate(np.array([100.0, 0.1]), np.array([2.0, -1.0]))
    np.testing.assert_allclose(outside, [tables[-1, -1], tables[0, 0]], atol=1e-15)


def test_a_seed_reproduces_the_samples_and_floaters_and_rejections_keep_their_reasons(setup):
    scenario, robot, q = setup
    Q = q + np.linspace(0.0, 0.02, 40)[:, None] * np.array([1.0, -0.5, 0.3, 0.0, 0.2, 0.0])
    T = np.arange(40) * 5e-4
    runs = [IioctSensor(robot, mode="distance", floater_rate=0.3, seed=s).samples(Q, Q, T) for s in (5, 5, 6)]
    fields = lambda xs: [(x.t_s, x.distance_mm, x.valid, x.reason, *x.p_W) for x in xs]  # noqa: E731
    np.testing.assert_equal(fields(runs[0]), fields(runs[1]))  # NaN equal to NaN
    assert [x.distance_mm for x in runs[0]] != [x.distance_mm for x in runs[2]]
    # floaters: confident wrong distances well short of the retina (30 % of 40 samples)
    short = [x for x in runs[0] if x.valid and x.distance_mm < x.true_distance_mm - 0.2]
    assert 3 <= len(short) <= 25 and all(x.confidence > 0 for x in short)
    # a model the beam meets more obliquely than allowed: every sample rejected as "incidence"
    oblique = IioctSensor(robot, mode="distance", max_incidence_rad=1e-3).samples(Q, Q, T, model=scenario.eye.ellipsoid)
    assert all(not x.valid and x.reason == "incidence" and np.isnan(x.p_W).all() for x in oblique)
    # no retina within the engine's depth: "no_retina"
    short_range = IioctSensor(robot, mode="distance")
    short_range.max_distance_mm = 1.0
    assert all(x.reason == "no_retina" and not x.valid for x in short_range.samples(Q[:5], Q[:5], T[:5]))
    # bad rows among good ones (NaN, infinite): only those samples are invalid
    Qbad = Q[:5].copy()
    Qbad[2, 3], Qbad[4, 0] = np.nan, -np.inf
    mixed = IioctSensor(robot, mode="distance").samples(Qbad, Q[:5], T[:5])
    assert [x.reason.startswith("bad_joint_state") for x in mixed] == [False, False, True, False, True]
    assert [x.t_s for x in mixed] == T[:5].tolist()


def test_a_packet_holds_its_samples_as_arrays_row_by_row(setup):
    """One packet with every kind of sample (valid, floater, low confidence, incidence,
    bad joint state): the arrays agree with each other (NaN distance and point exactly
    where invalid, the point on the reported beam to 1e-12 mm, "" exactly where valid)
    and with its SensorSamples field by field, with the same Python types as a
    SensorSample's; `take` picks rows; a deep copy is the packet itself."""
    scenario, robot, q = setup
    Q = q + np.linspace(0.0, 0.02, 40)[:, None] * np.array([1.0, -0.5, 0.3, 0.0, 0.2, 0.0])
    Q[[3, 17], 2] = np.nan
    T = np.arange(40) * 5e-4
    sensor = IioctSensor(robot, mode="distance", floater_rate=0.3, max_incidence_rad=np.radians(21.0), seed=5)
    p = sensor.packet(Q, Q, T, model=scenario.eye.ellipsoid)
    assert isinstance(p, SensorPacket) and p.n_samples == 40 and p.ascans is None
    assert {"", "incidence", "low_confidence", BAD_JOINT_STATE} <= set(p.reasons)
    np.testing.assert_array_equal(p.t_s, T)
    np.testing.assert_array_equal(np.isnan(p.distance_mm), ~p.valid)
    np.testing.assert_array_equal(np.isnan(p.p_W).any(axis=1), ~p.valid)
    np.testing.assert_array_equal([r == "" for r in p.reasons], p.valid)
    np.testing.assert_array_equal(p.confidence, np.where(p.valid, DISTANCE_MODE_CONFIDENCE, 0.0))
    np.testing.assert_allclose(p.p_W[p.valid], (p.beam_origin_W + p.distance_mm[:, None] * p.beam_dir_W)[p.valid],
                               rtol=0, atol=1e-12)
    assert np.isnan(p.beam_origin_W[[3, 17]]).all() and np.isnan(p.true_distance_mm[[3, 17]]).all()
    for k, s in enumerate(p.samples()):
        assert [type(x) for x in (s.t_s, s.distance_mm, s.valid, s.confidence, s.reason, s.true_distance_mm)] == [
            float, float, bool, float, str, float]
        np.testing.assert_equal(tuple(s), (p.t_s[k], p.distance_mm[k], p.valid[k], p.confidence[k], p.reasons[k],
                                           p.p_W[k], p.beam_origin_W[k], p.beam_dir_W[k], None, p.true_distance_mm[k]))
    assert p.sample(-1).t_s == T[-1] and copy.deepcopy(p) is p
    with pytest.raises(ValueError, match=r"\[-40, 39\]"):
        p.sample(40)
    part = p.take(np.array([17, 0]))
    assert part.n_samples == 2 and part.reasons == (BAD_JOINT_STATE, p.reasons[0])
    np.testing.assert_array_equal(part.p_W, p.p_W[[17, 0]])


@pytest.fixture(scope="module")
def robots():
    """{eye name: Robot}: an ellipsoidal and a star-shaped (composite) true retina."""
    return {name: Robot(SurgeryScenario(eye_name=name)) for name in ("emmetropic", "detached")}


@pytest.mark.parametrize("floater_rate", [0.0, 0.3])
@pytest.mark.parametrize("eye_name", ["emmetropic", "detached"])
def test_a_distance_packet_is_the_numpy_reference_computation_of_its_draws(robots, eye_name, floater_rate):
    """The compiled "distance" packet against a NumPy reference from the same seed (M
    uniforms, M standard normals, with floaters 2 x M uniforms; sample m takes the m-th):
    beams from Robot.beam, true distances from Eye.ray_cast, the error model's tables
    interpolated by SciPy (clamped to the grid), the draws, floaters and points written
    out. 40 samples moving 0.02 rad in runs of 1 to 3 equal rows (as the sensor's latches
    repeat them), the reported angles 1e-4 rad off the true ones (equal to them in every
    fifth row), the range cut at the median true distance (half "no_retina") and p_invalid raised by 0.3
    (some "low_confidence"). Distances, true distances, points and beams agree to 1e-12
    mm, validity, reasons and confidences exactly, and the generator is left where the
    reference's is. The incidence is Eye.beam_hits' (tests/models/test_eyes.py holds it
    to the ray cast and the surface normal; the composite eyes' normal is a finite
    difference, matching surface_normal's to ~1e-9 only, which moves the interpolated
    bias by ~1e-11 mm)."""
    robot = robots[eye_name]
    eye = robot.scenario.eye
    q = start_posture(robot, robot.scenario.eye_pose.to_W(np.array([[1.0, 2.0, -3.0]]))[0], robot.scenario.p_WC)
    M, runs = 40, np.resize([1, 2, 3, 2], 20)
    Q = q + np.repeat(np.linspace(0.0, 0.02, len(runs)), runs)[:, None] * np.array([1.0, -0.5, 0.3, 0.0, 0.2, 0.0])
    Q_reported = Q + 1e-4 * np.sin(np.arange(6 * M).reshape(M, 6))
    Q_reported[::5] = Q[::5]
    sensor = IioctSensor(robot, mode="distance", floater_rate=floater_rate, seed=11)
    m = sensor.error_model
    sensor.error_model = dataclasses.replace(m, p_invalid=np.minimum(np.array(m.p_invalid) + 0.3, 1.0).tolist())
    beams = lambda Qs, true: [np.array(x) for x in zip(*(robot.beam(q, true=true) for q in Qs))]  # noqa: E731
    (O_true, U_true), (O, U) = beams(Q, True), beams(Q_reported, False)
    d_true = eye.ray_cast(O_true, U_true)
    incidence = eye.beam_hits(O_true, U_true)[1]
    sensor.max_distance_mm = float(np.median(d_true))
    rng = np.random.default_rng(11)
    uniform, normal = rng.random(M), rng.standard_normal(M)
    floater_draws = rng.random((2, M)) if floater_rate > 0 else np.ones((2, M))
    D, A = np.array(m.distances_mm), np.array(m.incidences_rad)
    tables = np.stack([sensor.error_model.p_invalid, m.bias, m.sd], axis=-1)
    p_invalid, bias, sd = RegularGridInterpolator((D, A), tables)(
        np.column_stack([np.clip(d_true, D[0], D[-1]), np.clip(incidence, A[0], A[-1])])).T
    live = d_true <= sensor.max_distance_mm
    valid = live & (uniform >= p_invalid)
    d = np.where(valid, d_true + bias + sd * normal, np.nan)
    floater = live & (floater_draws[0] < floater_rate) & (d_true > 1.0)
    d = np.where(floater, 0.5 + (d_true - 1.0) * floater_draws[1], d)
    valid |= floater
    reasons = np.where(~live, "no_retina", np.where(valid, "", "low_confidence")).tolist()

    p = sensor.packet(Q, Q_reported, np.arange(M) * 5e-4)
    assert set(reasons) == {"", "no_retina", "low_confidence"} and floater.any() == (floater_rate > 0)
    np.testing.assert_array_equal(p.valid, valid)
    assert list(p.reasons) == reasons
    np.testing.assert_array_equal(p.confidence, np.where(valid, DISTANCE_MODE_CONFIDENCE, 0.0))
    for got, want in ((p.true_distance_mm, d_true), (p.distance_mm, d), (p.p_W, O + d[:, None] * U),
                      (p.beam_origin_W, O), (p.beam_dir_W, U)):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)  # NaN where NaN
    assert sensor._rng.random() == rng.random()


@pytest.mark.parametrize("eye_name", ["emmetropic", "detached"])
def test_each_sample_of_a_packet_is_what_it_gives_alone(robots, eye_name):
    """Runs of 1 to 3 equal rows, as the sensor's latches repeat them (one with a joint at
    0.0, -0.0, 0.0); reported rows equal to the true ones, off them in a whole run, in part
    of one, or repeating the row before across a run's end: the compiled packet (which
    evaluates the chain and casts the ray once per run of equal rows) gives every sample,
    every array bit for bit, as a packet of that sample alone with the same draws
    (floaters included); so do the beams (`sensor_beams`)."""
    robot = robots[eye_name]
    q = start_posture(robot, robot.scenario.eye_pose.to_W(np.array([[1.0, 2.0, -3.0]]))[0], robot.scenario.p_WC)
    M, runs = 24, np.resize([1, 2, 3], 12)  # runs start at rows 0, 1, 3, 6, 7, 9, 12, 13, 15, 18, 19, 21
    Q = q + np.repeat(np.linspace(0.0, 0.02, len(runs)), runs)[:, None] * np.array([1.0, -0.5, 0.3, 0.0, 0.2, 0.0])
    Q[3:6, 3] = 0.0, -0.0, 0.0
    Q_reported = Q.copy()
    Q_reported[9:12] += 1e-4  # a run off the true rows
    Q_reported[13] -= 1e-4  # the first row of a run off
    Q_reported[18] = Q_reported[17]  # the row before, across a run's end
    sensor = IioctSensor(robot, mode="distance", floater_rate=0.3, seed=2)
    rng = np.random.default_rng(2)
    uniform, normal, floater_draws = rng.random(M), rng.standard_normal(M), rng.random((2, M))
    packet = sensor._distance_arrays(Q, Q_reported, uniform, normal, floater_draws)
    chain = robot.chain
    beams = sensor_beams(chain.S, Q, Q_reported, *chain.homes["S_true"], *sensor._home_Scal)
    for m in range(M):
        alone = sensor._distance_arrays(Q[m:m + 1], Q_reported[m:m + 1], uniform[m:m + 1], normal[m:m + 1],
                                        floater_draws[:, m:m + 1])
        assert [a[m].tobytes() for a in packet] == [a[0].tobytes() for a in alone]
        beams_alone = sensor_beams(chain.S, Q[m:m + 1], Q_reported[m:m + 1], *chain.homes["S_true"],
                                   *sensor._home_Scal)
        assert [b[m].tobytes() for b in beams] == [b[0].tobytes() for b in beams_alone]
    assert len({tuple(o) for o in beams[0]}) == len(runs)  # the runs were there


def test_an_ascan_mode_packet_holds_the_a_scans_of_the_samples_with_a_retina(setup):
    scenario, robot, q = setup
    Q = np.array([q, q, np.full(6, np.nan)])
    p = IioctSensor(robot, mode="ascan", seed=1).packet(Q, Q, [0.0, 5e-4, 1e-3])
    assert p.valid[:2].all() and p.reasons[2] == BAD_JOINT_STATE
    assert [None if a is None else a.shape for a in p.ascans] == [p.ascans[0].shape] * 2 + [None]
    assert p.sample(1).ascan is p.ascans[1]


class _Recorder(LeafSystem):
    """Brute-force reference: records (t, q) at every sample time with a discrete update
    at 2 kHz (the phase in which the sensor's q is read) into a Python list."""

    def __init__(self, rate_hz: float):
        super().__init__()
        self.rows: list = []
        self._q = self.DeclareVectorInputPort("q", 6)
        self.DeclareDiscreteState(1)
        self.DeclarePeriodicDiscreteUpdateEvent(1.0 / rate_hz, 0.0, self._record)

    def _record(self, context, discrete_state) -> None:
        self.rows.append((context.get_time(), np.array(self._q.Eval(context))))


@pytest.mark.parametrize("offset_s", [0.0, 0.0013])
def test_the_block_delivers_exactly_the_brute_force_reference_samples(setup, offset_s):
    """q changing at every sample (a 2 kHz integrator): each packet appears once, 10
    samples with the reference's time stamps (bit for bit) and beams at the reference's
    joint angles; with the same seed the samples equal the sensor's on the reference
    packets, field by field. With a time offset (2.6 samples: the first packets' points
    from before the first sample, held at it) the reported angles are the reference's
    history interpolated at t - offset."""
    scenario, robot, q = setup
    b = DiagramBuilder()
    src = b.AddSystem(ConstantVectorSource(np.array([0.05, -0.03, 0.02, 0.0, 0.04, 0.1])))
    integ = b.AddSystem(DiscreteTimeIntegrator(6, 5e-4))
    sensor = b.AddSystem(IioctSensorSystem(IioctSensor(robot, mode="distance", seed=0), 2000.0, offset_s, packet=10))
    rec = b.AddSystem(_Recorder(2000.0))
    b.Connect(src.get_output_port(), integ.get_input_port())
    for sink in (sensor.GetInputPort("q"), rec.get_input_port()):
        b.Connect(integ.get_output_port(), sink)
    sim = Simulator(b.Build())
    integ.set_integral_value(integ.GetMyMutableContextFromRoot(sim.get_mutable_context()), q)
    packets = []
    for n in range(12):  # read between each packet event (t_last + 0.125 ms) and the next sample
        sim.AdvanceTo(n * 5e-3 + 4.8e-3)
        packets.append(sensor.GetOutputPort("packet").Eval(sensor.GetMyContextFromRoot(sim.get_context())))
    assert len({p.t_s[0] for p in packets}) == 12
    reference = IioctSensor(robot, mode="distance", seed=0)
    for n, packet in enumerate(packets):
        T = np.array([t for t, _ in rec.rows[10 * n:10 * n + 10]])
        Q = np.array([qq for _, qq in rec.rows[10 * n:10 * n + 10]])
        assert packet.t_s.tolist() == T.tolist()
        assert len(set(map(tuple, Q))) == 10  # q really changes at every sample
        t_all, q_all = np.array([t for t, _ in rec.rows]), np.array([qq for _, qq in rec.rows])
        Q_reported = np.column_stack([np.interp(T - offset_s, t_all, q_all[:, i]) for i in range(6)])
        r = reference.packet(Q, Q_reported, T)
        for name in ("distance_mm", "valid", "reasons", "true_distance_mm", "beam_origin_W", "p_W"):
            np.testing.assert_equal(getattr(packet, name), getattr(r, name))  # NaN equal to NaN


def test_a_run_started_late_packs_only_the_samples_recorded_since_its_start(setup):
    """A simulation starting at 3.1 ms: its first packet (processed at 4.625 ms) holds the
    samples at 3.5, 4.0 and 4.5 ms only (k x 0.5 ms, Drake's sample times), none of the
    register's unrecorded rows; with a 1.3 ms offset their points come from the first
    sample's joint angles (the history starts there)."""
    scenario, robot, q = setup
    qdot = np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0])  # rad/s
    sim, sensor = _moving_diagram(robot, q, qdot, 0.0013)
    sim.get_mutable_context().SetTime(0.0031)
    sim.Initialize()
    sim.AdvanceTo(0.0049)
    packet = sensor.GetOutputPort("packet").Eval(sensor.GetMyContextFromRoot(sim.get_context()))
    assert packet.t_s.tolist() == (np.arange(7, 10) * 5e-4).tolist()
    first = IioctSensor(robot, mode="distance").reported_beams(np.array([q]))[0][0]  # q at 3.5 ms: the integral's start
    np.testing.assert_array_equal(packet.beam_origin_W, np.tile(first, (3, 1)))


def test_a_run_started_after_a_packets_last_sample_has_no_packet_until_the_next(setup):
    """Started at 4.6 ms, between the last sample of the first packet (4.5 ms) and its
    event (4.625 ms): no sample yet at 4.9 ms (measurement t_s = -inf, not valid); at
    9.9 ms the packet of 5.0-9.5 ms."""
    scenario, robot, q = setup
    sim, sensor = _moving_diagram(robot, q, np.zeros(6), 0.0)
    sim.get_mutable_context().SetTime(0.0046)
    sim.Initialize()
    sim.AdvanceTo(0.0049)
    ctx = sensor.GetMyContextFromRoot(sim.get_context())
    m = sensor.GetOutputPort("measurement").Eval(ctx)
    assert m[3] == -np.inf and m[1] == 0.0
    sim.AdvanceTo(0.0099)
    packet = sensor.GetOutputPort("packet").Eval(sensor.GetMyContextFromRoot(sim.get_context()))
    assert packet.t_s.tolist() == (np.arange(10, 20) * 5e-4).tolist()


@pytest.mark.parametrize("packet", [10, 20])
@pytest.mark.parametrize("offset_s", [0.0, 0.0013])
def test_a_block_latching_1_khz_joint_angles_delivers_the_2_khz_registers_packets(setup, offset_s, packet):
    """q from a 1 kHz integrator into a block told so (input_rate_hz=1000: latches at whole
    ms) and a block with the default 2 kHz register: the same packets, every field bit for
    bit (NaN equal to NaN), each once. The default block processes a packet a quarter
    sample after its last sample, the 1 kHz one after the latch at the next whole ms
    (1.25 samples after it); each block is read between its processing and the next."""
    scenario, robot, q = setup
    b = DiagramBuilder()
    src = b.AddSystem(ConstantVectorSource(np.array([0.05, -0.03, 0.02, 0.0, 0.04, 0.1])))
    integ = b.AddSystem(DiscreteTimeIntegrator(6, 1e-3))
    blocks = [b.AddSystem(IioctSensorSystem(IioctSensor(robot, mode="distance", seed=0), 2000.0, offset_s, packet,
                                            input_rate_hz=rate)) for rate in (None, 1000.0)]
    b.Connect(src.get_output_port(), integ.get_input_port())
    for block in blocks:
        b.Connect(integ.get_output_port(), block.GetInputPort("q"))
    sim = Simulator(b.Build())
    integ.set_integral_value(integ.GetMyMutableContextFromRoot(sim.get_mutable_context()), q)
    assert [block.packet_offset_s for block in blocks] == [(packet - 0.75) * 5e-4, (packet + 0.25) * 5e-4]
    packets = ([], [])
    for n in range(8):
        for block, out in zip(blocks, packets):
            sim.AdvanceTo(n * packet * 5e-4 + block.packet_offset_s + 1e-4)
            out.append(block.GetOutputPort("packet").Eval(block.GetMyContextFromRoot(sim.get_context())))
    for default, latched in zip(*packets):
        for name in SensorPacket._fields:
            np.testing.assert_equal(getattr(latched, name), getattr(default, name))  # NaN equal to NaN
    assert [p.t_s.tolist() for p in packets[1]] == [(np.arange(n * packet, (n + 1) * packet) * 5e-4).tolist()
                                                    for n in range(8)]
    d = packets[1][1].true_distance_mm  # samples 2j - 1 and 2j alike (q changes after each whole ms), no more
    assert d[1::2].tolist() == d[2::2].tolist() + [d[-1]] and len(set(d.tolist())) == packet // 2 + 1


def test_an_input_rate_that_does_not_divide_the_sample_rate_is_refused(setup):
    """So is a packet that is no multiple of the samples per latch."""
    scenario, robot, q = setup
    for input_rate_hz in (3000.0, 0.0, np.nan, 1500.0):
        with pytest.raises(ValueError, match=r"input_rate_hz must be rate_hz / r .*2000, 1000, 666.667, \.\.\. Hz"):
            IioctSensorSystem(IioctSensor(robot), 2000.0, input_rate_hz=input_rate_hz)
    with pytest.raises(ValueError, match="packet must be a multiple of rate_hz / input_rate_hz = 2 samples"):
        IioctSensorSystem(IioctSensor(robot), 2000.0, packet=5, input_rate_hz=1000.0)


@pytest.mark.parametrize("start_s, first", [(0.0031, 7), (0.0036, 8), (0.0046, 10)])
def test_a_run_started_late_on_1_khz_joint_angles_packs_only_the_samples_since_its_start(setup, start_s, first):
    """q integrated and latched at 1 kHz, the packet of 0-4.5 ms processed at 5.125 ms. A
    run started mid-packet, at 3.1 or 3.6 ms, packs the samples from its start on (3.5 or
    4.0 ms to 4.5 ms: at 3.6 ms the 4 ms latch covers the 3.5 ms sample too, which is
    left out), with a 1.3 ms offset their points from the first sample's joint angles
    (the history starts there); a run started at 4.6 ms, after the packet's last sample
    (which the 5 ms latch covers), has no packet until the next, that of 5.0-9.5 ms."""
    scenario, robot, q = setup
    sim, sensor = _moving_diagram(robot, q, np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0]), 0.0013, input_rate_hz=1000.0)
    sim.get_mutable_context().SetTime(start_s)
    sim.Initialize()
    sim.AdvanceTo(sensor.packet_offset_s + 2e-4)
    ctx = sensor.GetMyContextFromRoot(sim.get_context())
    packet, m = sensor.GetOutputPort("packet").Eval(ctx), sensor.GetOutputPort("measurement").Eval(ctx)
    if first < 10:
        assert packet.t_s.tolist() == (np.arange(first, 10) * 5e-4).tolist()
        beam_at_start = IioctSensor(robot, mode="distance").reported_beams(np.array([q]))[0][0]
        np.testing.assert_array_equal(packet.beam_origin_W, np.tile(beam_at_start, (10 - first, 1)))
    else:
        assert m[3] == -np.inf and m[1] == 0.0
    sim.AdvanceTo(sensor.packet_offset_s + 5.2e-3)
    packet = sensor.GetOutputPort("packet").Eval(sensor.GetMyContextFromRoot(sim.get_context()))
    assert packet.t_s.tolist() == (np.arange(10, 20) * 5e-4).tolist()



@settings(max_examples=20, deadline=None)
@given(start_s=st.floats(0.0, 0.012), input_rate_hz=st.sampled_from([None, 1000.0]),
       offset_s=st.sampled_from([0.0, 0.0013]))
def test_a_full_registers_fast_read_is_the_general_one(setup, start_s, input_rate_hz, offset_s):
    """A run started at a random time, q moving at every latch: at each of the first 6
    packet events after the start `_recorded` gives, bit for bit, the arrays of
    `_recorded_since_start` (the general read, filtered by the run's start time): through
    the general read for the first packet or two (the sentinel not yet recorded), through
    its precomputed indices from the third on."""
    scenario, robot, q = setup
    sim, sensor = _moving_diagram(robot, q, np.array([0.05, -0.03, 0.02, 0.0, 0.04, 0.1]), offset_s, input_rate_hz)
    processor = next(s for s in sensor.GetSystems() if isinstance(s, _PacketProcessor))
    sim.get_mutable_context().SetTime(start_s)
    sim.Initialize()
    general = []
    with mock.patch.object(processor, "_recorded_since_start", wraps=processor._recorded_since_start) as since_start:
        first = int(np.floor((start_s - sensor.packet_offset_s) / 5e-3)) + 1  # the first packet event after the start
        for t in sensor.packet_offset_s + 5e-3 * np.arange(max(first, 0), max(first, 0) + 6):
            sim.AdvanceTo(t)
            context = processor.GetMyContextFromRoot(sim.get_context())
            calls = since_start.call_count
            T, Q = processor._recorded(context)
            general.append(since_start.call_count > calls)
            T_ref, Q_ref = since_start(context)
            assert T.tobytes() == T_ref.tobytes() and Q.tobytes() == Q_ref.tobytes()
            assert Q.shape == (len(T), 6) and Q.flags.c_contiguous
    assert general[0] and not any(general[2:])
