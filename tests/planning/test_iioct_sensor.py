"""The iiOCT sensor on the robot: true beam on the true eye, point from the reported
angles and the calibrated pose, in both modes against NumPy references (Robot.beam,
Eye.ray_cast, the error model's tables, the A-scan chain); distance mode = the full
chain's statistics; packets as arrays; runs of equal joint-angle rows."""
from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.interpolate import RegularGridInterpolator

from models.iioct import Floater, synthesize_ascan
from models.iioct.error_model import extractor_error_model
from planning import Robot, SurgeryScenario, start_posture
from planning.iioct import BAD_JOINT_STATE, DISTANCE_MODE_CONFIDENCE, IioctSensor, SensorPacket
from planning.iioct.kernels import row_runs, sensor_beams


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


def _moving_rows(robot):
    """(Q, Q_reported) (40, 6) rad: 40 samples moving 0.02 rad in runs of 1 to 3 equal rows
    (as the sensor's latches repeat them), the reported angles 1e-4 rad off the true ones
    (equal to them in every fifth row)."""
    q = start_posture(robot, robot.scenario.eye_pose.to_W(np.array([[1.0, 2.0, -3.0]]))[0], robot.scenario.p_WC)
    M, runs = 40, np.resize([1, 2, 3, 2], 20)
    Q = q + np.repeat(np.linspace(0.0, 0.02, len(runs)), runs)[:, None] * np.array([1.0, -0.5, 0.3, 0.0, 0.2, 0.0])
    Q_reported = Q + 1e-4 * np.sin(np.arange(6 * M).reshape(M, 6))
    Q_reported[::5] = Q[::5]
    return Q, Q_reported


def _reference_geometry(robot, Q, Q_reported):
    """(O, U (M, 3): calibrated beams from Robot.beam at Q_reported; d_true (M,) mm from
    Eye.ray_cast along the true beams Robot.beam(true=True) at Q; incidence (M,) rad,
    Eye.beam_hits' on those beams)."""
    beams = lambda Qs, true: [np.array(x) for x in zip(*(robot.beam(q, true=true) for q in Qs))]  # noqa: E731
    (O_true, U_true), (O, U) = beams(Q, True), beams(Q_reported, False)
    eye = robot.scenario.eye
    return O, U, eye.ray_cast(O_true, U_true), eye.beam_hits(O_true, U_true)[1]


@pytest.mark.parametrize("floater_rate", [0.0, 0.3])
@pytest.mark.parametrize("eye_name", ["emmetropic", "detached"])
def test_a_distance_packet_is_the_numpy_reference_computation_of_its_draws(robots, eye_name, floater_rate):
    """The compiled "distance" packet against a NumPy reference from the same seed (M
    uniforms, M standard normals, with floaters 2 x M uniforms; sample m takes the m-th):
    the reference geometry (`_reference_geometry`), the error model's tables
    interpolated by SciPy (clamped to the grid), the draws, floaters and points written
    out. The rows of `_moving_rows`, the range cut at the median true distance (half
    "no_retina") and p_invalid raised by 0.3 (some "low_confidence"). Distances, true
    distances, points and beams agree to 1e-12 mm, validity, reasons and confidences
    exactly, and the generator is left where the reference's is. The incidence is
    Eye.beam_hits' (tests/models/test_eyes.py holds it to the ray cast and the surface
    normal; the composite eyes' normal is a finite difference, matching
    surface_normal's to ~1e-9 only, which moves the interpolated bias by ~1e-11 mm)."""
    robot = robots[eye_name]
    Q, Q_reported = _moving_rows(robot)
    M = len(Q)
    sensor = IioctSensor(robot, mode="distance", floater_rate=floater_rate, seed=11)
    m = sensor.error_model
    sensor.error_model = dataclasses.replace(m, p_invalid=np.minimum(np.array(m.p_invalid) + 0.3, 1.0).tolist())
    O, U, d_true, incidence = _reference_geometry(robot, Q, Q_reported)
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


@pytest.mark.parametrize("floater_rate", [0.0, 0.3])
@pytest.mark.parametrize("eye_name", ["emmetropic", "detached"])
def test_an_ascan_packet_is_the_a_scan_chain_on_the_reference_geometry(robots, eye_name, floater_rate):
    """The "ascan" packet against the A-scan chain run sample by sample on the reference
    geometry (`_reference_geometry`) from the same seed: a sample with the retina in range
    draws, in order, its floater (with floaters, on beams longer than 1 mm: a uniform
    against the rate, then its depth and strength) and its A-scan (models.iioct
    .synthesize_ascan at the true distance and incidence), which the extractor reads; its
    point lies on the calibrated beam at the extracted distance. The rows of
    `_moving_rows`, the range cut at the median true distance (half "no_retina").
    Validity and reasons exactly; distances, points and A-scans to 1e-9 (the reference's
    true distances are Eye.ray_cast's, equal to 1e-12 mm); beams and true distances to
    1e-12 mm; the generator left where the reference's is."""
    robot = robots[eye_name]
    Q, Q_reported = _moving_rows(robot)
    M = len(Q)
    sensor = IioctSensor(robot, mode="ascan", floater_rate=floater_rate, seed=11)
    O, U, d_true, incidence = _reference_geometry(robot, Q, Q_reported)
    sensor.max_distance_mm = float(np.median(d_true))
    rng = np.random.default_rng(11)
    d, valid, reasons, ascans, n_floaters = np.full(M, np.nan), np.zeros(M, dtype=bool), [], [], 0
    for k in range(M):
        if not d_true[k] <= sensor.max_distance_mm:
            reasons.append("no_retina")
            ascans.append(None)
            continue
        floaters = ()
        if floater_rate > 0 and d_true[k] > 1.0 and rng.random() < floater_rate:
            floaters = (Floater(float(rng.uniform(0.5, d_true[k] - 0.5)), float(rng.uniform(35.0, 55.0))),)
            n_floaters += 1
        ascans.append(synthesize_ascan(float(d_true[k]), float(incidence[k]), rng, engine=sensor.engine,
                                       floaters=floaters))
        x = sensor.extractor(ascans[-1])
        valid[k], reasons = x.valid, reasons + ["" if x.valid else x.reason]
        d[k] = x.distance_mm if x.valid else np.nan

    p = sensor.packet(Q, Q_reported, np.arange(M) * 5e-4)
    assert "no_retina" in reasons and valid.any() and (n_floaters > 0) == (floater_rate > 0)
    np.testing.assert_array_equal(p.valid, valid)
    assert list(p.reasons) == reasons
    for got, want in ((p.distance_mm, d), (p.p_W, O + d[:, None] * U)):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)  # NaN where NaN
    for got, want in ((p.true_distance_mm, d_true), (p.beam_origin_W, O), (p.beam_dir_W, U)):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)
    assert [a is None for a in p.ascans] == [a is None for a in ascans]
    for got, want in zip(p.ascans, ascans):
        if want is not None:
            np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)
    assert sensor._rng.random() == rng.random()


@settings(max_examples=60)
@given(rows=st.lists(st.lists(st.sampled_from([0.0, -0.0, 1.0, np.nan]), min_size=2, max_size=2), min_size=1,
                     max_size=12))
def test_row_runs_are_the_runs_of_equal_consecutive_rows(rows):
    """Against NumPy: a run starts at row 0 and wherever a row differs from the one
    before (NaN equals nothing, -0.0 equals 0.0)."""
    Q = np.array(rows)
    starts_run = np.array([m == 0 or not np.array_equal(Q[m], Q[m - 1]) for m in range(len(Q))])
    starts, run = row_runs(Q)
    np.testing.assert_array_equal(starts, np.flatnonzero(starts_run))
    np.testing.assert_array_equal(run, np.cumsum(starts_run) - 1)


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
    packet = sensor.distance_arrays(Q, Q_reported, uniform, normal, floater_draws)
    beams = sensor_beams(*sensor.frames, Q, Q_reported)
    for m in range(M):
        alone = sensor.distance_arrays(Q[m:m + 1], Q_reported[m:m + 1], uniform[m:m + 1], normal[m:m + 1],
                                       floater_draws[:, m:m + 1])
        assert [a[m].tobytes() for a in packet] == [a[0].tobytes() for a in alone]
        beams_alone = sensor_beams(*sensor.frames, Q[m:m + 1], Q_reported[m:m + 1])
        assert [b[m].tobytes() for b in beams] == [b[0].tobytes() for b in beams_alone]
    assert len({tuple(o) for o in beams[0]}) == len(runs)  # the runs were there


def test_an_ascan_mode_packet_holds_the_a_scans_of_the_samples_with_a_retina(setup):
    scenario, robot, q = setup
    Q = np.array([q, q, np.full(6, np.nan)])
    p = IioctSensor(robot, mode="ascan", seed=1).packet(Q, Q, [0.0, 5e-4, 1e-3])
    assert p.valid[:2].all() and p.reasons[2] == BAD_JOINT_STATE
    assert [None if a is None else a.shape for a in p.ascans] == [p.ascans[0].shape] * 2 + [None]
    assert p.sample(1).ascan is p.ascans[1]
