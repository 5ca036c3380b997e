"""The local model's sd calibration (models.local.calibration): factors measured on held-out
predictions make the stated quantile of the errors lie within k calibrated sd, never
shrink the sd, never fall with the gap, and enter the field's sd exactly."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import norm

from models import Sphere
from models.local.calibration import SigmaCalibration
from models.local.field import LocalField
from models.local.field_kernels import CAL, CAL_KNOTS_RAD, N_CAL
from models.local.grid import LocalRetinaModel


def predictions_at(gap_deg, z, sd=0.05, r=11.0):
    """Rows of field_kernels.predictions: measured r, the field's r + z sd, sd, gap."""
    n = len(z)
    out = np.full((n, 6), np.nan)
    out[:, 0], out[:, 1], out[:, 2], out[:, 3] = r, r + z * sd, sd, np.radians(gap_deg)
    return out


def test_an_understated_sd_is_scaled_to_cover_the_quantile():
    """Errors drawn with twice the stated sd at a knot (5 deg): the 99 % quantile of |z| is
    2 x 2.576, so the factor is 2 x 2.576 / 3 = 1.72 (within the histogram's 0.05 cells and
    the sample quantile's spread: 20,000 draws, about +-0.03); the knots nearer the data,
    without evidence, keep 1, those further take 1.72 (never falling with the gap)."""
    cal = SigmaCalibration()
    z = np.random.default_rng(0).normal(0.0, 2.0, 20000)
    cal.absorb(predictions_at(5.0, z))
    f = cal.factors
    j = int(np.flatnonzero(np.isclose(CAL_KNOTS_RAD, np.radians(5.0)))[0])
    assert f[:j] == pytest.approx(1.0)
    assert f[j] == pytest.approx(2.0 * norm.ppf(0.995) / 3.0, abs=0.05 + 0.03)
    assert (f[j:] == f[j]).all()


def test_a_calibrated_sd_is_not_shrunk():
    cal = SigmaCalibration()
    cal.absorb(predictions_at(2.0, np.random.default_rng(1).normal(0.0, 0.3, 5000)))
    assert (cal.factors == 1.0).all()


@settings(max_examples=20)
@given(scale=st.lists(st.floats(0.1, 6.0), min_size=N_CAL, max_size=N_CAL), n=st.integers(0, 400))
def test_factors_are_at_least_one_and_never_fall_with_the_gap(scale, n):
    cal = SigmaCalibration()
    rng = np.random.default_rng(n)
    for knot, s in zip(np.degrees(CAL_KNOTS_RAD), scale):
        cal.absorb(predictions_at(knot, rng.normal(0.0, s, n)))
    f = cal.factors
    assert (f >= 1.0).all() and (np.diff(f) >= 0.0).all()
    assert (f[cal.count < cal.min_count] == np.maximum.accumulate(np.r_[1.0, f])[:-1][cal.count < cal.min_count]).all()


def test_old_evidence_fades():
    """A knot's counts halve past `memory`: after many small errors, the factor that large
    early errors set falls back (the model improved)."""
    cal = SigmaCalibration(memory=2000.0)
    cal.absorb(predictions_at(1.0, np.random.default_rng(2).normal(0.0, 3.0, 1000)))
    assert cal.factors[1] > 2.0
    cal.absorb(predictions_at(1.0, np.random.default_rng(3).normal(0.0, 0.5, 20000)))
    assert cal.factors[1] == 1.0


def test_non_finite_and_skipped_rows_are_ignored():
    cal = SigmaCalibration()
    rows = predictions_at(1.0, np.ones(10))
    rows[::2] = np.nan
    rows[1, 2] = 0.0  # no sd
    cal.absorb(rows)
    assert cal.count.sum() == pytest.approx(4.0)


@pytest.mark.parametrize("bad", [dict(k=0.0), dict(quantile=1.0), dict(min_count=0.0), dict(memory=100.0),
                                 dict(max_factor=1.0), dict(width=0.0)])
def test_bad_settings_are_refused(bad):
    with pytest.raises(ValueError, match="SigmaCalibration"):
        SigmaCalibration(**bad)


def test_the_field_multiplies_its_sd_by_the_factor_at_its_gap():
    """The same model's field with every factor 2 answers twice the sd and the same distance."""
    rng = np.random.default_rng(4)
    u = rng.normal(size=(3000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    u = u[u[:, 2] < -0.6]
    m = LocalRetinaModel(np.zeros(3))
    m.update((11.0 + rng.normal(0.0, 0.02, len(u)))[:, None] * u, Sphere(np.zeros(3), 11.1))
    m.solve_all()
    f1 = m.field()
    params = f1.params.copy()
    params[CAL:CAL + N_CAL] = 2.0
    f2 = LocalField(params, f1.kind)
    Q = 10.5 * u[::10]
    h1, _, s1 = f1.signed_distance_gradient_uncertainty(Q)
    h2, _, s2 = f2.signed_distance_gradient_uncertainty(Q)
    np.testing.assert_allclose(h2, h1, atol=1e-12)
    np.testing.assert_allclose(s2, 2.0 * s1, rtol=1e-12)
