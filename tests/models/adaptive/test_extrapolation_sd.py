"""The robust globe's own sd far from the data (models.adaptive.extrapolation.extrapolation_sd):
it is the least-squares fit's sd, checked against the spread of fits to independent noise,
and it grows as the data see less of the globe."""
from __future__ import annotations

import numpy as np
import pytest

from models.adaptive.extrapolation import extrapolation_sd
from models.fit.ellipsoid_fit import LENGTH_SCALE_MM
from models.fit.quadric_kernels import add_weighted_design_rows, fit_ellipsoid_scatter

RADII_MM = np.array([12.3, 12.0, 11.9])  # an eye's globe (models.eyes: the detached eye's)
NOISE_MM = 0.02


def cap_directions(cap_deg, n, seed):
    """n unit directions uniform over the cap within cap_deg of the posterior pole (-z)."""
    rng = np.random.default_rng(seed)
    cz = rng.uniform(np.cos(np.radians(cap_deg)), 1.0, n)
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    s = np.sqrt(1.0 - cz * cz)
    return np.stack([s * np.cos(phi), s * np.sin(phi), -cz], axis=1)


def on_globe(u):
    """The points of the ellipsoid RADII_MM about the origin along unit directions u."""
    return (1.0 / np.sqrt(np.sum((u / RADII_MM) ** 2, axis=1)))[:, None] * u


def globe_points(u, noise_rng):
    """on_globe(u), noisy along the normal (NOISE_MM)."""
    P = on_globe(u)
    n = P / RADII_MM ** 2
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return P + noise_rng.normal(0.0, NOISE_MM, len(P))[:, None] * n


def fit(P, p0):
    S = np.zeros((10, 10))
    add_weighted_design_rows(S, P, p0, LENGTH_SCALE_MM, np.ones(len(P)))
    code, v, c, r, R = fit_ellipsoid_scatter(S, p0, LENGTH_SCALE_MM, True)
    assert code == 0
    return S, v, c, r, R


def sd_of(cap_deg, n=400, seed=0):
    P = globe_points(cap_directions(cap_deg, n, seed), np.random.default_rng(seed + 100))
    p0 = P[0].copy()
    S, v, c, r, R = fit(P, p0)
    return extrapolation_sd(S, v, c, r, R, p0, LENGTH_SCALE_MM, 5.0)


def test_it_is_the_spread_of_fits_to_independent_noise():
    """Fits to the same 400 directions (a 60 deg cap) with fresh noise: the sd of their
    distance from the true globe, at the retina's points, peaks at extrapolation_sd's value
    (first order: within 25 % over 300 fits, whose sd itself scatters by ~4 %)."""
    u = cap_directions(60.0, 400, 1)
    p0 = globe_points(u[:1], np.random.default_rng(0))[0]
    # the retina's points: directions within 115 deg of the posterior pole (the cap the crop leaves)
    g = np.random.default_rng(5).normal(size=(4000, 3))
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    g = g[g[:, 2] <= np.cos(np.radians(65.0))]
    Q = on_globe(g)
    d, predicted = [], []
    for k in range(300):
        S, v, c, r, R = fit(globe_points(u, np.random.default_rng(1000 + k)), p0)
        predicted.append(extrapolation_sd(S, v, c, r, R, p0, LENGTH_SCALE_MM, 5.0))
        # the fitted surface's distance at Q along the normal, to first order: Q / |grad Q| of the fit
        X = (Q - p0) / LENGTH_SCALE_MM
        x, y, z = X.T
        q = v[0] * x * x + v[1] * y * y + v[2] * z * z + 2 * (v[3] * y * z + v[4] * x * z + v[5] * x * y
                                                              + v[6] * x + v[7] * y + v[8] * z) + v[9]
        gx = 2 * (v[0] * x + v[5] * y + v[4] * z + v[6])
        gy = 2 * (v[5] * x + v[1] * y + v[3] * z + v[7])
        gz = 2 * (v[4] * x + v[3] * y + v[2] * z + v[8])
        d.append(q / np.sqrt(gx * gx + gy * gy + gz * gz) * LENGTH_SCALE_MM)
    empirical = np.std(np.array(d), axis=0).max()
    assert np.median(predicted) == pytest.approx(empirical, rel=0.25)


def test_it_grows_as_the_data_see_less_of_the_globe():
    sds = [sd_of(cap) for cap in (30.0, 45.0, 60.0, 90.0)]
    assert all(a > b for a, b in zip(sds, sds[1:]))
    assert sds[0] > 10 * sds[-1]  # a 30 deg cap leaves the equator to a long lever
    assert sds[-1] < 0.05  # a hemisphere's globe: tens of um at most, from 20 um noise
    assert sd_of(60.0, n=1600) == pytest.approx(sd_of(60.0, n=400) / 2.0, rel=0.2)  # 1 / sqrt(n)


def test_no_points_no_sd():
    S = np.zeros((10, 10))
    v = np.zeros(10)
    v[:3], v[9] = 1.0, -1.0
    assert extrapolation_sd(S, v, np.zeros(3), np.ones(3), np.eye(3), np.zeros(3), 1.0, 5.0) == np.inf
