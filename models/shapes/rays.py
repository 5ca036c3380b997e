"""What every beam cast on a placed surface shares (compiled with numba): the rays taken
from W into the surface's frame E, checked, and the incidence of a ray on a surface.

Units: mm, rad; frames W and E (X_WE = (R_WE, p_WE)).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models.shapes.validation import as_points

UNIT_TOL = 1e-6  # |  |u| - 1 | of a unit direction, as Eye.ray_cast allows


def as_rays(O_W, U_W) -> tuple[np.ndarray, np.ndarray]:
    """(O_W, U_W) as C-contiguous float (M, 3) arrays (ray origins mm, directions), or a
    ValueError naming the shapes allowed. Finiteness and unit length are checked by
    `rays_in_frame`, in the compiled pass."""
    O, U = np.ascontiguousarray(O_W, dtype=float), np.ascontiguousarray(U_W, dtype=float)
    if O.ndim != 2 or O.shape[1] != 3 or U.shape != O.shape:
        raise ValueError(f"O_W and U_W must be (M, 3) arrays of one shape (origins mm, unit directions), "
                         f"got {O.shape} and {U.shape}")
    return O, U


def unit_rays(origins, dirs) -> tuple[np.ndarray, np.ndarray]:
    """(origins, dirs) as finite float (M, 3) arrays of one shape (a single (3,) ray: one
    row), the directions of unit length within UNIT_TOL; ValueError naming them otherwise
    (what a shape's `ray_cast` takes)."""
    O, D = as_points(origins, "origins"), as_points(dirs, "dirs")
    if O.shape != D.shape:
        raise ValueError(f"origins and dirs must have the same shape, got {O.shape} and {D.shape}")
    if np.any(np.abs(np.linalg.norm(D, axis=1) - 1.0) > UNIT_TOL):
        raise ValueError(f"dirs must be unit vectors (| |u| - 1 | <= {UNIT_TOL:g})")
    return O, D


@njit(cache=True)
def rays_in_frame(O_W, U_W, p_WE, R_WE):
    """(O_E, U_E) (M, 3): the rays with origins O_W (M, 3) mm and unit directions U_W
    (M, 3) in W, expressed in the frame E at (R_WE (3, 3), p_WE (3,) mm). ValueError if an
    origin is not finite or a direction's length differs from 1 by more than UNIT_TOL."""
    M = O_W.shape[0]
    O_E, U_E = np.empty((M, 3)), np.empty((M, 3))
    for m in range(M):
        n2 = U_W[m, 0] * U_W[m, 0] + U_W[m, 1] * U_W[m, 1] + U_W[m, 2] * U_W[m, 2]
        if not abs(np.sqrt(n2) - 1.0) <= UNIT_TOL:
            raise ValueError("U_W must be unit directions (| |u| - 1 | <= 1e-6)")
        if not (np.isfinite(O_W[m, 0]) and np.isfinite(O_W[m, 1]) and np.isfinite(O_W[m, 2])):
            raise ValueError("O_W must be finite origins (mm)")
        for k in range(3):
            O_E[m, k] = ((O_W[m, 0] - p_WE[0]) * R_WE[0, k] + (O_W[m, 1] - p_WE[1]) * R_WE[1, k]
                         + (O_W[m, 2] - p_WE[2]) * R_WE[2, k])
            U_E[m, k] = U_W[m, 0] * R_WE[0, k] + U_W[m, 1] * R_WE[1, k] + U_W[m, 2] * R_WE[2, k]
    return O_E, U_E


@njit(cache=True, error_model="numpy")
def incidence_rad(n_dot_u, n_norm):
    """The incidence (rad, in [0, pi/2]) of a ray with unit direction u on a surface with
    normal n (either sense) from n . u and |n| > 0: arccos(|n . u| / |n|), the cosine
    clamped at 1 against rounding."""
    return np.arccos(min(1.0, abs(n_dot_u) / n_norm))


@njit(cache=True, error_model="numpy")
def incidences_rad(N, U):
    """(M,) `incidence_rad` of the unit directions U (M, 3) on the normals N (M, 3), any
    length > 0, in one frame."""
    out = np.empty(N.shape[0])
    for m in range(N.shape[0]):
        out[m] = incidence_rad(N[m, 0] * U[m, 0] + N[m, 1] * U[m, 1] + N[m, 2] * U[m, 2],
                               np.sqrt(N[m, 0] * N[m, 0] + N[m, 1] * N[m, 1] + N[m, 2] * N[m, 2]))
    return out


def beam_incidences_rad(shape, O_W, U_W) -> np.ndarray:
    """(M,) incidence (rad) of the beams (origins O_W, unit directions U_W (M, 3) in W, mm)
    on `shape` (anything with ray_cast and gradient in W: Sphere, Ellipsoid, Eye) where
    each first meets it; 0 where a beam misses it."""
    O, U = np.ascontiguousarray(O_W, dtype=float), np.ascontiguousarray(U_W, dtype=float)
    d = np.asarray(shape.ray_cast(O, U), dtype=float)
    out = np.zeros(len(d))
    hit = np.isfinite(d)
    if hit.any():
        G = np.asarray(shape.gradient(O[hit] + d[hit, None] * U[hit]), dtype=float)
        out[hit] = incidences_rad(np.ascontiguousarray(G), U[hit])
    return out
