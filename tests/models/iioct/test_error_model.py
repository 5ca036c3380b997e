"""The extractor's error model (models.iioct.error_model): tabulated from the full chain,
interpolated bilinearly and clamped, drawn with its bias, SD and invalid fraction."""
from __future__ import annotations

import numpy as np

from models.iioct.error_model import extractor_error_model


def test_the_error_model_is_tabulated_from_the_extractor():
    m = extractor_error_model()
    normal = [m.bias[i][0] for i in range(len(m.distances_mm))]
    assert max(abs(b) for b in normal) <= 0.005  # |bias| <= 5 um at normal incidence
    assert max(m.sd[i][0] for i in range(len(m.distances_mm))) <= 0.020  # SD <= 20 um
    assert m.p_invalid[-1][-1] > 0.5  # 25 mm at 75 deg: mostly invalid


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
