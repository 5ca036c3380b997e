"""Where the fibre never looked: the retina an ellipsoid fit has to extrapolate to.

Points and quadrics are in the fits' scaled coordinates (models.ellipsoid_fit).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models._kernels import sampson_distances, sampson_one
from models.sampling import unit_sphere_grid

_DIRECTIONS = unit_sphere_grid(12, 24)  # 288 directions over the whole surface


@njit(cache=True)
def _drift_and_gap(D, center, radii, rotation, anterior_dir, crop, v_old, c_sf, r_sf):
    """Over the points X = center + rotation (radii * d) of an ellipsoid, d the rows of D
    (K, 3) (equal-area directions), without the cap within `crop` of its extreme point
    along `anterior_dir` (the part the metrics ignore): (the mean Sampson distance of X
    from the quadric v_old (10,), the mean |(|X - c_sf| - r_sf)| (distance from the sphere),
    the number of points used). Scaled coordinates; one pass, no temporary arrays but X."""
    K = D.shape[0]
    X = np.empty((K, 3))
    h = np.empty(K)
    h_max = -np.inf
    for k in range(K):
        a0, a1, a2 = D[k, 0] * radii[0], D[k, 1] * radii[1], D[k, 2] * radii[2]
        for i in range(3):
            X[k, i] = center[i] + (a0 * rotation[i, 0] + a1 * rotation[i, 1] + a2 * rotation[i, 2])
        h[k] = ((X[k, 0] - center[0]) * anterior_dir[0] + (X[k, 1] - center[1]) * anterior_dir[1]
                + (X[k, 2] - center[2]) * anterior_dir[2])
        h_max = max(h_max, h[k])
    drift, gap, m = 0.0, 0.0, 0
    for k in range(K):
        if h[k] <= h_max - crop:
            x, y, z = X[k, 0], X[k, 1], X[k, 2]
            drift += sampson_one(v_old, x, y, z)
            dx, dy, dz = x - c_sf[0], y - c_sf[1], z - c_sf[2]
            gap += abs(np.sqrt(dx * dx + dy * dy + dz * dz) - r_sf)
            m += 1
    return (drift / m, gap / m, m) if m else (np.nan, np.nan, 0)


def drift_and_gap(center, radii, rotation, anterior_dir, crop, v_old, c_sf, r_sf) -> tuple[float, float, int]:
    """(mean drift, mean gap, K) over the K points of the ellipsoid (center (3,), radii (3,),
    rotation (3, 3)) in _DIRECTIONS, equal-area, without the cap within `crop` of its
    extreme point along the unit `anterior_dir` (the part the metrics ignore): the drift is
    the Sampson distance from the quadric v_old (10,), the gap the distance from the sphere
    (c_sf (3,), r_sf). All in the fits' scaled coordinates; NaNs and K = 0 when the cap
    covers the whole ellipsoid."""
    return _drift_and_gap(_DIRECTIONS, center, radii, rotation, anterior_dir, crop, v_old, c_sf, r_sf)


def sampson_distance(v: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(K,) first-order distance |Q(x)| / |grad Q(x)| of points X (K, 3) from quadric v (10,)
    (inf where the gradient vanishes); the compiled one the outlier gate uses."""
    return sampson_distances(v, X)
