"""The plate calibration's standard errors: they describe the errors it makes, and the
filter's default declared bound covers three of them.

Over independent noise draws, (error / standard error)^2 of the origin's three
coordinates and the beam's two angles is chi-square with 5 degrees of freedom in all:
the mean over 6 draws (30 terms) lies within [0.4, 1.9] x 5 with probability > 99 %
(chi-square 30 dof / 6: 2.5 % and 99.5 % quantiles 16.8 / 6 and 53.7 / 6)."""
from __future__ import annotations

import numpy as np

from models.calibration.plate import Plane, SensorPose, calibrate_sensor, offset_sensor_pose, plate_distances, \
    sample_flange_poses
from models.calibration.uncertainty import calibration_uncertainty
from safety import FilterConfig

NOMINAL = SensorPose([62.0, 0.0, 0.0], [1.0, 0.0, 0.0])
PLATE = Plane([0.0, 0.0, 1.0], -50.0)
CENTRE = (250.0, 0.0, 50.0)


def calibrated(seed: int):
    rng = np.random.default_rng(seed)
    truth = offset_sensor_pose(NOMINAL, 0.3, np.radians(2.0), rng)
    R, t = sample_flange_poses(250, NOMINAL, PLATE, rng, centre_W=CENTRE)
    m = plate_distances(R, t, truth, PLATE, 20.0, rng)
    result = calibrate_sensor(R, t, m)
    return truth, result, calibration_uncertainty(R, t, m, result)


def test_the_standard_errors_describe_the_errors_and_the_default_bound_covers_three():
    z2, bounds = [], []
    for seed in range(6):
        truth, result, u = calibrated(seed)
        e = result.sensor.p_FS - truth.p_FS
        along = e @ truth.u_F
        angle = np.arccos(np.clip(result.sensor.u_F @ truth.u_F, -1, 1))
        # across the beam and the direction: two coordinates each, sharing the variance
        z2.append(along**2 / u.along_mm**2 + (e @ e - along**2) / (u.across_mm**2 / 2)
                  + angle**2 / (np.radians(u.direction_deg) ** 2 / 2))
        bounds.append(u.bound(3.0))
    assert 0.4 * 5 <= np.mean(z2) <= 1.9 * 5
    mm, deg = np.mean(bounds, axis=0)
    config = FilterConfig()
    assert config.calibration_bound_mm >= mm and config.calibration_bound_deg >= deg
