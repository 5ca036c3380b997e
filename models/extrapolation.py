"""Where the fibre never looked: the retina an ellipsoid fit has to extrapolate to.

Points and quadrics are in the fits' scaled coordinates (models.ellipsoid_fit).
"""
from __future__ import annotations

import numpy as np

from models._kernels import sampson_distances
from models.sampling import unit_sphere_grid

_DIRECTIONS = unit_sphere_grid(12, 24)  # 288 directions over the whole surface


def global_surface_points(center, radii, rotation, anterior_dir, crop) -> np.ndarray:
    """(K, 3) points on an ellipsoid, equal-area in direction, without the cap within
    `crop` of its extreme point along `anterior_dir` (the part the metrics ignore)."""
    X = center + (_DIRECTIONS * radii) @ rotation.T
    h = (X - center) @ anterior_dir
    return X[h <= h.max() - crop]


def sampson_distance(v: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(K,) first-order distance |Q(x)| / |grad Q(x)| of points X (K, 3) from quadric v (10,)
    (inf where the gradient vanishes); the compiled one the outlier gate uses."""
    return sampson_distances(v, X)
