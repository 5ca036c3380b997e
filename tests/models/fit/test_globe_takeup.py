"""When the robust globe becomes the quadric under the local model
(models.adaptive.model.AdaptiveEyeModel._globe_taken): only once the data tell it from the
sphere (GLOBE_DEPARTURE), which is when it has become the more accurate of the two; and on
a detached eye, whose least-squares ellipsoid the criteria never take, within the lag target
of the point after which it stays the more accurate (the paper spiral, one A-scan at a time)."""
from __future__ import annotations

import numpy as np
import pytest

from eval.experiments.paper import MAX_LAG
from models import AdaptiveEyeModel
from models.adaptive.model import GLOBE_DEPARTURE
from models.adaptive.transition import PredictiveCriteria
from models.eyes import make_eye
from models.local.grid import LocalRetinaModel
from models.metrics import mae_exact
from models.scan.paper_scan import paper_scan

N_CHECKS = 100  # points along the spiral where both quadrics' MAE is measured (the paper's curves)


def _spiral(shape: str, seed: int):
    """(take-ups, curve): at each update where the globe is taken up, (fraction of the spiral,
    its departure from the sphere mm, its rms sd x GLOBE_SD_FACTOR mm, its MAE mm, the
    sphere's MAE mm); at N_CHECKS points, (fraction, the globe's MAE, the sphere's MAE)."""
    eye = make_eye(shape)
    P = paper_scan(eye, seed=seed).points
    truth = eye.reference_samples(40, 40)
    model = AdaptiveEyeModel(PredictiveCriteria(), local=LocalRetinaModel(eye.pose.p_WE))
    checks = set(np.linspace(0, len(P) - 1, N_CHECKS).round().astype(int).tolist())
    take_ups, curve, was_taken = [], [], False
    for i, p in enumerate(P):
        model.update(p)
        fit = model.globe.last_ok
        if model.globe_taken and not was_taken:
            gap, sd = model.globe_departure_mm
            take_ups.append(((i + 1) / len(P), gap, sd, mae_exact(fit.ellipsoid, truth).mean,
                             mae_exact(model.sphere, truth).mean))
        was_taken = model.globe_taken
        if i in checks and fit is not None:
            curve.append(((i + 1) / len(P), mae_exact(fit.ellipsoid, truth).mean, mae_exact(model.sphere, truth).mean))
    return take_ups, np.array(curve)


@pytest.mark.parametrize("seed", [0, 4])
def test_a_globe_the_data_cannot_tell_from_the_sphere_is_not_taken_up(seed):
    """The myopic eye: from 9 % of the spiral its globe predicts the newest points better
    than the sphere while over the retina it is 3-20 x less accurate (0.4-2.9 mm against
    0.1 mm) until ~28 %; it differs from the sphere by less than its own uncertainty then
    (seed 4: the most of nine seeds, 1.71 x GLOBE_SD_FACTOR x its rms sd). No take-up of a
    globe less accurate than the sphere; seed 0 took one at 17 % before the departure test."""
    take_ups, _ = _spiral("myopic", seed)
    for at, gap, sd, globe_mae, sphere_mae in take_ups:
        assert gap > GLOBE_DEPARTURE * sd
        assert globe_mae < sphere_mae, f"globe taken at {at:.3f} with MAE {globe_mae:.3f} mm (sphere {sphere_mae:.3f})"


def test_a_detached_eyes_globe_is_taken_up_within_the_lag_target():
    """The detached eye (seed 1: of nine seeds, the one whose globe passed the departure
    test the latest, at 19 %): its globe is taken up after the first point from which it
    stays more accurate than the sphere and within MAX_LAG (10 %) of the spiral after it,
    each take-up with the globe the more accurate."""
    take_ups, curve = _spiral("detached", 1)
    at, globe_mae, sphere_mae = curve.T
    worse = np.flatnonzero(~(globe_mae < sphere_mae))
    optimal = at[worse[-1] + 1]
    assert len(take_ups) >= 1
    first = take_ups[0][0]
    assert optimal - 1.0 / N_CHECKS <= first <= optimal + MAX_LAG
    for _, gap, sd, g, s in take_ups:
        assert gap > GLOBE_DEPARTURE * sd and g < s
