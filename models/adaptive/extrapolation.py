"""Where the fibre never looked: the retina an ellipsoid fit has to extrapolate to.

Points and quadrics are in the fits' scaled coordinates (models.fit.ellipsoid_fit).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models.fit.quadric_residuals import sampson_one
from models.shapes.sampling import unit_sphere_grid

_DIRECTIONS = unit_sphere_grid(12, 24)  # 288 directions over the whole surface


@njit(cache=True, error_model="numpy")  # a zero length divides as NumPy divides: inf, NaN
def _drift_and_gap(D, center_mm, radii_mm, rotation, p0, scale, S, crop_mm, v_old, c_sf_mm, r_sf_mm):
    """drift_and_gap over the directions D (K, 3). All in the fits' scaled coordinates
    ((x - p0) / scale, computed element by element as NumPy's array arithmetic computes
    them, and the anterior direction's length by np.dot, NumPy's own: the crop test of a
    point can hang on its last bits); one pass, no temporary arrays but X and the heights
    h along the anterior direction."""
    center, radii, anterior, c_sf = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    for i in range(3):
        center[i] = (center_mm[i] - p0[i]) / scale
        radii[i] = radii_mm[i] / scale
        # from the points' centroid to the centre: the scanned retina lies opposite the front of the eye
        anterior[i] = center[i] - S[6 + i, 9] / (2.0 * S[9, 9])
        c_sf[i] = (c_sf_mm[i] - p0[i]) / scale
    anterior_norm = np.sqrt(np.dot(anterior, anterior))
    for i in range(3):
        anterior[i] /= anterior_norm
    crop, r_sf = crop_mm / scale, r_sf_mm / scale
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
    cut = h_max - crop
    drift, gap, m = 0.0, 0.0, 0
    for k in range(K):
        if h[k] <= cut:
            x, y, z = X[k, 0], X[k, 1], X[k, 2]
            drift += sampson_one(v_old, x, y, z)
            dx, dy, dz = x - c_sf[0], y - c_sf[1], z - c_sf[2]
            gap += abs(np.sqrt(dx * dx + dy * dy + dz * dz) - r_sf)
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
