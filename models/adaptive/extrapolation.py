"""Where the fibre never looked: the retina an ellipsoid fit has to extrapolate to.

Points and quadrics are in the fits' scaled coordinates (models.fit.ellipsoid_fit).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models.fit.quadric_kernels import design_row
from models.fit.quadric_residuals import half_gradient, sampson_one
from models.fit.small_linalg import cholesky, dot, lower_inverse, mat_vec
from models.shapes.sampling import unit_sphere_grid
from models.shapes.sphere import sphere_distance_one

_DIRECTIONS = unit_sphere_grid(12, 24)  # 288 directions over the whole surface


@njit(cache=True, error_model="numpy", inline="always")  # a zero length divides as NumPy divides: inf, NaN
def _retina(D, center_mm, radii_mm, rotation, p0, scale, S, crop_mm):
    """(X (K, 3), keep (K,)): the points of the ellipsoid (center_mm, radii_mm, rotation)
    along the directions D (K, 3) and whether each is on the retina (not in the cap within
    crop_mm of its extreme point along the anterior direction: from the centroid of S's
    points to the centre, the scanned retina lying opposite the front of the eye). In the
    fits' scaled coordinates ((x - p0) / scale, computed element by element as NumPy's array
    arithmetic computes them, and the anterior direction's length by np.dot, NumPy's own: the
    crop test of a point can hang on its last bits)."""
    center, radii, anterior = np.empty(3), np.empty(3), np.empty(3)
    for i in range(3):
        center[i] = (center_mm[i] - p0[i]) / scale
        radii[i] = radii_mm[i] / scale
        anterior[i] = center[i] - S[6 + i, 9] / (2.0 * S[9, 9])
    anterior_norm = np.sqrt(np.dot(anterior, anterior))
    for i in range(3):
        anterior[i] /= anterior_norm
    K = D.shape[0]
    X = np.empty((K, 3))
    h = np.empty(K)
    h_max = -np.inf
    for k in range(K):
        a0, a1, a2 = D[k, 0] * radii[0], D[k, 1] * radii[1], D[k, 2] * radii[2]
        for i in range(3):
            X[k, i] = center[i] + (a0 * rotation[i, 0] + a1 * rotation[i, 1] + a2 * rotation[i, 2])
        h[k] = ((X[k, 0] - center[0]) * anterior[0] + (X[k, 1] - center[1]) * anterior[1]
                + (X[k, 2] - center[2]) * anterior[2])
        h_max = max(h_max, h[k])
    return X, h <= h_max - crop_mm / scale


@njit(cache=True, error_model="numpy")
def _drift_and_gap(D, center_mm, radii_mm, rotation, p0, scale, S, crop_mm, v_old, c_sf_mm, r_sf_mm):
    """drift_and_gap over the directions D (K, 3), on the points of _retina."""
    X, keep = _retina(D, center_mm, radii_mm, rotation, p0, scale, S, crop_mm)
    c_sf = np.empty(3)
    for i in range(3):
        c_sf[i] = (c_sf_mm[i] - p0[i]) / scale
    r_sf = r_sf_mm / scale
    drift, gap, m = 0.0, 0.0, 0
    for k in range(D.shape[0]):
        if keep[k]:
            x, y, z = X[k, 0], X[k, 1], X[k, 2]
            drift += sampson_one(v_old, x, y, z)
            gap += abs(sphere_distance_one(c_sf, r_sf, x, y, z)[0])
            m += 1
    return (drift / m, gap / m, m) if m else (np.nan, np.nan, 0)


def drift_and_gap(center_mm, radii_mm, rotation, p0, scale, S, crop_mm, v_old, c_sf_mm, r_sf_mm) -> tuple[float, float, int]:
    """(mean drift, mean gap, K) over the K points of the ellipsoid (center_mm (3,), radii_mm
    (3,) mm, rotation (3, 3)) in _DIRECTIONS, equal-area, without the cap within crop_mm of
    its extreme point along the anterior direction, from the centroid of the points of the
    scatter matrix S to the centre (the part the metrics ignore): the drift is the Sampson
    distance from the quadric v_old (10,), the gap the distance from the sphere (c_sf_mm
    (3,), r_sf_mm mm). The quadric, S and the results are in the fits' scaled coordinates
    ((x - p0) / scale, p0 (3,) mm); NaNs and K = 0 when the cap covers the whole ellipsoid."""
    return _drift_and_gap(_DIRECTIONS, center_mm, radii_mm, rotation, p0, scale, S, crop_mm, v_old, c_sf_mm, r_sf_mm)


_SD_DIRECTIONS = unit_sphere_grid(8, 16)  # 128 directions: the leverage is smooth over the surface


@njit(cache=True)
def _extrapolation_sd(D, S, v, center_mm, radii_mm, rotation, p0, scale, crop_mm):
    """extrapolation_sd over the directions D (K, 3)."""
    n = np.sqrt(dot(v, v))
    vh = v / n
    q2 = dot(v, mat_vec(S, v))
    if not (S[9, 9] > 0.0 and n > 0.0):
        return np.inf
    var = max(q2, 0.0) / S[9, 9]  # the mean square algebraic residual (weighted)
    P = np.eye(10)
    for i in range(10):
        for j in range(10):
            P[i, j] -= vh[i] * vh[j]
    A = P @ S @ P
    alpha = 0.0
    for i in range(10):
        alpha += A[i, i]
    for i in range(10):  # the fitted quadric's own direction, fixed by the normalisation: any positive weight
        for j in range(10):
            A[i, j] += alpha / 10.0 * vh[i] * vh[j]
    L, ok = cholesky(A)
    if not ok:
        return np.inf
    Li = lower_inverse(L)
    X, keep = _retina(D, center_mm, radii_mm, rotation, p0, scale, S, crop_mm)
    m, q, y = np.empty(10), np.empty(10), np.empty(10)
    worst = 0.0
    for k in range(D.shape[0]):
        if not keep[k]:
            continue
        x0, x1, x2 = X[k, 0], X[k, 1], X[k, 2]
        design_row(x0, x1, x2, m)
        c = dot(vh, m)
        for i in range(10):
            q[i] = m[i] - c * vh[i]
        for i in range(10):  # y = L^-1 q: lev = |y|^2
            s = 0.0
            for j in range(i + 1):
                s += Li[i, j] * q[j]
            y[i] = s
        h0, h1, h2 = half_gradient(v, x0, x1, x2)
        g0, g1, g2 = 2.0 * h0, 2.0 * h1, 2.0 * h2
        g = np.sqrt(g0 * g0 + g1 * g1 + g2 * g2) / n
        worst = max(worst, np.sqrt(var * dot(y, y) / (n * n)) / g)
    return worst * scale


def extrapolation_sd(S, v, center_mm, radii_mm, rotation, p0, scale, crop_mm) -> float:
    """The largest standard deviation (mm), over the retina (the ellipsoid without the cap
    within crop_mm of its extreme point along the anterior direction, as drift_and_gap), of
    the distance from the quadric v (10,) fitted to the weighted scatter matrix S (10, 10)
    (the ellipsoid center_mm, radii_mm, rotation), were the fit's residuals independent
    noise: the least-squares covariance (v^T S v / sum w) (P S P)^+ of the coefficients
    (P: off v, which the normalisation fixes) carried to each point's Sampson distance. Far
    from the data it grows with how little of the globe they see (the leverage). inf when
    S holds no points or is singular off v. Scaled coordinates as drift_and_gap."""
    return _extrapolation_sd(_SD_DIRECTIONS, S, v, center_mm, radii_mm, rotation, p0, scale, crop_mm)


@njit(cache=True, error_model="numpy")
def _largest_gaps(D, S, center_mm, radii_mm, rotation, p0, scale, crop_mm, c_sf_mm, r_sf_mm, v_other, p0_other, has_other):
    """largest_gaps over the directions D (K, 3)."""
    X, keep = _retina(D, center_mm, radii_mm, rotation, p0, scale, S, crop_mm)
    to_sphere, to_other = 0.0, 0.0
    for k in range(D.shape[0]):
        if not keep[k]:
            continue
        x0, x1, x2 = p0[0] + scale * X[k, 0], p0[1] + scale * X[k, 1], p0[2] + scale * X[k, 2]  # mm
        to_sphere = max(to_sphere, abs(sphere_distance_one(c_sf_mm, r_sf_mm, x0, x1, x2)[0]))
        if has_other:  # in the other quadric's scaled coordinates
            to_other = max(to_other, scale * sampson_one(v_other, (x0 - p0_other[0]) / scale, (x1 - p0_other[1]) / scale,
                                                         (x2 - p0_other[2]) / scale))
    return to_sphere, to_other


def largest_gaps(S, center_mm, radii_mm, rotation, p0, scale, crop_mm, sphere, v_other=None, p0_other=None
                 ) -> tuple[float, float]:
    """(to the sphere, to the other quadric) mm: the largest distance over the retina of the
    ellipsoid (center_mm, radii_mm, rotation; the retina as drift_and_gap's, its anterior
    direction from the points of the scatter matrix S, scaled coordinates about p0 (3,) mm)
    from the Sphere `sphere` (exact) and from the quadric v_other (10,), in the scaled
    coordinates about p0_other (3,) mm (its Sampson distance, models.fit.quadric_residuals,
    which exceeds the true one by about d^2 / 2r: 0.3 mm at 3 mm on a 12 mm globe; 0.0
    without one)."""
    has = v_other is not None
    return _largest_gaps(_DIRECTIONS, S, center_mm, radii_mm, rotation, p0, scale, crop_mm, sphere.center,
                         float(sphere.radius), v_other if has else _NO_QUADRIC, p0_other if has else _ZERO3, has)


_NO_QUADRIC, _ZERO3 = np.zeros(10), np.zeros(3)
