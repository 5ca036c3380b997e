"""Plate calibration of the sensor pose: exact recovery, the design's targets, invariances.

Physics behind the tolerances: distance noise N(0, 20 um) along the beam appears in
the point-to-plane residual scaled by the cosine of the incidence angle, so the RMS
residual is 20 um x sqrt(mean cos^2) (8 fitted degrees of freedom of 250 poses take
1.6 % off), about 14.6 um for the sampler's 65 deg cone; its sampling SD with 250
poses is ~0.7 um. Without noise the problem is exact: SLSQP (ftol 1e-12 on the mean
squared residual in um^2) must land within 1e-6 mm of the truth.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from models.calibration.plate import (
    Plane,
    SensorPose,
    calibrate_sensor,
    direction_error_deg,
    offset_sensor_pose,
    plate_distances,
    position_error_um,
    sample_flange_poses,
)

NOMINAL = SensorPose([62.0, 0.0, 0.0], [1.0, 0.0, 0.0])
PLATE = Plane([0.0, 0.0, 1.0], -50.0)
CENTRE = (250.0, 0.0, 50.0)


def setup(seed, noise_um=20.0, n=250, nominal=NOMINAL, offset_mm=0.3, tilt_deg=2.0):
    rng = np.random.default_rng(seed)
    truth = offset_sensor_pose(nominal, offset_mm, np.radians(tilt_deg), rng)
    R, t = sample_flange_poses(n, nominal, PLATE, rng, centre_W=CENTRE)
    m = plate_distances(R, t, truth, PLATE, noise_um, rng)
    return truth, R, t, m


@pytest.fixture(scope="module")
def noisy():
    truth, R, t, m = setup(seed=7)
    return truth, R, t, m, calibrate_sensor(R, t, m)


def test_noisy_recovery_meets_the_targets(noisy):
    truth, R, _, _, res = noisy
    assert position_error_um(res.sensor, truth) <= 20.0
    assert direction_error_deg(res.sensor, truth) <= 0.1
    assert res.residual_rms_um < 30.03
    cos = np.abs(truth.beams_W(R) @ PLATE.normal_W)
    expected_rms = 20.0 * np.sqrt(np.mean(cos**2) * (1 - 8 / len(R)))
    assert abs(res.residual_rms_um - expected_rms) < 2.5
    assert res.residual_max_um >= res.residual_rms_um
    # the plate itself is recovered (normal facing the sensor)
    assert np.degrees(np.arccos(min(1.0, res.plane.normal_W @ PLATE.normal_W))) < 0.05
    assert abs(res.plane.signed_distance(np.array(CENTRE))[0]) < 0.02
    assert res.n_starts == 18 and res.converged and 1 <= res.n_at_best <= 18 and res.solve_time_s > 0


def test_noise_free_recovery_is_exact():
    truth, R, t, m = setup(seed=1, noise_um=0.0)
    res = calibrate_sensor(R, t, m)
    assert position_error_um(res.sensor, truth) < 1e-3  # 1e-6 mm
    assert direction_error_deg(res.sensor, truth) < np.degrees(1e-6)
    assert res.residual_max_um < 1e-3


@settings(max_examples=8)
@given(
    seed=st.integers(0, 10_000),
    u=st.sampled_from([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0], [0.6, 0.0, -0.8]]),
    offset_mm=st.floats(0.0, 0.5),
    tilt_deg=st.floats(0.0, 5.0),
)
def test_noise_free_recovery_for_any_mounting(seed, u, offset_mm, tilt_deg):
    nominal = SensorPose([40.0, -5.0, 10.0], u)
    truth, R, t, m = setup(seed, noise_um=0.0, n=60, nominal=nominal, offset_mm=offset_mm, tilt_deg=tilt_deg)
    res = calibrate_sensor(R, t, m)
    assert position_error_um(res.sensor, truth) < 1e-2
    assert direction_error_deg(res.sensor, truth) < 1e-6


@settings(max_examples=5)
@given(rotvec=st.tuples(*[st.floats(-3.0, 3.0)] * 3), shift=st.tuples(*[st.floats(-500.0, 500.0)] * 3))
def test_result_is_invariant_to_the_world_frame(noisy, rotvec, shift):
    """Moving W (robot base) rigidly moves the plate with it and leaves p, u in F unchanged."""
    truth, R, t, m, res = noisy
    Q = Rotation.from_rotvec(rotvec).as_matrix()
    moved = calibrate_sensor(Q @ R, t @ Q.T + np.array(shift), m)
    assert position_error_um(moved.sensor, res.sensor) < 0.05
    assert direction_error_deg(moved.sensor, res.sensor) < 1e-5
    assert np.allclose(moved.residuals_mm, res.residuals_mm, atol=1e-7)
    assert np.allclose(moved.plane.normal_W, Q @ res.plane.normal_W, atol=1e-8)


def test_result_is_invariant_to_the_pose_order(noisy):
    truth, R, t, m, res = noisy
    k = np.random.default_rng(0).permutation(len(m))
    shuffled = calibrate_sensor(R[k], t[k], m[k])
    assert position_error_um(shuffled.sensor, res.sensor) < 0.05
    assert direction_error_deg(shuffled.sensor, res.sensor) < 1e-5


def test_sampler_aims_the_nominal_sensor_inside_its_design():
    rng = np.random.default_rng(3)
    R, t = sample_flange_poses(500, NOMINAL, PLATE, rng, max_tilt_deg=65.0, distance_range_mm=(2.0, 15.0), half_width_mm=20.0, centre_W=CENTRE)
    assert np.allclose(np.einsum("nji,njk->nik", R, R), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    m = plate_distances(R, t, NOMINAL, PLATE)
    assert m.min() >= 2.0 - 1e-9 and m.max() <= 15.0 + 1e-9
    incidence = np.degrees(np.arccos(-NOMINAL.beams_W(R) @ PLATE.normal_W))
    assert incidence.max() <= 65.0 + 1e-9 and incidence.max() > 60.0
    hits = NOMINAL.points_W(R, t, m)
    assert np.allclose(hits[:, 2], 50.0)  # on the plate, within the +-20 mm square (in-plane axes random)
    assert np.linalg.norm(hits[:, :2] - CENTRE[:2], axis=1).max() <= 20.0 * np.sqrt(2.0) + 1e-9
    # the plate normal seen from the flange must vary in all three directions (observability)
    a_F = np.einsum("nji,j->ni", R, PLATE.normal_W)
    assert np.linalg.svd(a_F - a_F.mean(axis=0), compute_uv=False)[-1] > 0.1 * np.sqrt(len(R))


@settings(max_examples=30)
@given(seed=st.integers(0, 10_000), offset_mm=st.floats(0.0, 2.0), tilt_deg=st.floats(0.0, 10.0))
def test_offset_sensor_pose_has_the_requested_error(seed, offset_mm, tilt_deg):
    truth = offset_sensor_pose(NOMINAL, offset_mm, np.radians(tilt_deg), np.random.default_rng(seed))
    assert position_error_um(truth, NOMINAL) == pytest.approx(1e3 * offset_mm, abs=1e-6)
    assert direction_error_deg(truth, NOMINAL) == pytest.approx(tilt_deg, abs=1e-9)


def test_plate_distances_refuses_beams_that_miss():
    R = np.tile(np.eye(3), (3, 1, 1))
    t = np.array([[0.0, 0.0, 60.0], [0.0, 0.0, 70.0], [0.0, 0.0, 80.0]])
    up = SensorPose([0.0, 0.0, 0.0], [0.0, 0.0, 1.0])  # pointing away from the plate below
    with pytest.raises(ValueError, match="do not reach the plane"):
        plate_distances(R, t, up, PLATE)
    down = SensorPose([0.0, 0.0, 0.0], [0.0, 0.0, -1.0])
    assert np.allclose(plate_distances(R, t, down, PLATE), [10.0, 20.0, 30.0])
    with pytest.raises(ValueError, match="rng"):
        plate_distances(R, t, down, PLATE, noise_um=5.0)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: SensorPose([0, 0, 0], [1.0, 0.1, 0]), "u_F must be a unit vector"),
        (lambda: SensorPose([0, np.nan, 0], [1.0, 0, 0]), "p_FS must be finite"),
        (lambda: Plane([0, 0, 2.0], 0.0), "normal_W must be a unit vector"),
        (lambda: Plane([0, 0, 1.0], np.inf), "offset_mm must be finite"),
        (lambda: offset_sensor_pose(NOMINAL, -0.1, 0.0, np.random.default_rng()), "offset_mm"),
        (lambda: sample_flange_poses(0, NOMINAL, PLATE, np.random.default_rng()), "n must be a positive integer"),
        (lambda: sample_flange_poses(5, NOMINAL, PLATE, np.random.default_rng(), max_tilt_deg=90.0), "max_tilt_deg"),
        (lambda: sample_flange_poses(5, NOMINAL, PLATE, np.random.default_rng(), distance_range_mm=(3.0, 1.0)), "distance_range_mm"),
    ],
)
def test_bad_arguments_name_themselves(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_translations_alone_are_refused_as_unobservable():
    rng = np.random.default_rng(2)
    R = np.tile(Rotation.from_rotvec([0.0, np.pi / 2, 0.0]).as_matrix(), (40, 1, 1))  # beam (F x) down
    t = np.column_stack([rng.uniform(-20, 20, (40, 2)), rng.uniform(115, 125, 40)])  # origin 3-13 mm above the plate
    m = plate_distances(R, t, NOMINAL, PLATE)
    with pytest.raises(ValueError, match="unobservable"):
        calibrate_sensor(R, t, m)


def test_calibrate_sensor_rejects_bad_data(noisy):
    _, R, t, m, _ = noisy
    with pytest.raises(ValueError, match="at least 10 poses"):
        calibrate_sensor(R[:9], t[:9], m[:9])
    bad = m.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match="distances_mm"):
        calibrate_sensor(R, t, bad)
    with pytest.raises(ValueError, match="R_WF"):
        calibrate_sensor(R * 1.01, t, m)
    with pytest.raises(ValueError, match="R_WF must be"):
        calibrate_sensor(R[:-1], t, m)
