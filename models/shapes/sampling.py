"""Equal-area direction grids for surface sampling (the paper's 500 x 500 sampling)."""
from __future__ import annotations

import numpy as np


def unit_sphere_grid(n_theta: int, n_phi: int, uz_max: float = 1.0) -> np.ndarray:
    """(n_theta * n_phi, 3) unit vectors, u_z uniform on [-1, uz_max] and azimuth uniform.

    Uniform u_z is equal-area on the unit sphere (Archimedes), so the grid weighs every
    part of a near-spherical surface alike; cell centres keep the poles from being
    sampled n_phi times over.
    """
    n_theta, n_phi = int(n_theta), int(n_phi)
    if n_theta < 2 or n_phi < 3:
        raise ValueError(f"need n_theta >= 2 and n_phi >= 3, got {n_theta}, {n_phi}")
    if not -1.0 < uz_max <= 1.0:
        raise ValueError(f"uz_max must be in (-1, 1], got {uz_max}")
    uz = -1.0 + (np.arange(n_theta) + 0.5) * (uz_max + 1.0) / n_theta
    phi = (np.arange(n_phi) + 0.5) * 2.0 * np.pi / n_phi
    s = np.sqrt(1.0 - uz**2)
    return np.stack(
        [np.outer(s, np.cos(phi)), np.outer(s, np.sin(phi)), np.repeat(uz[:, None], n_phi, 1)], axis=-1
    ).reshape(-1, 3)
