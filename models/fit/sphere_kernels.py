"""Compiled kernels of the sphere filter (models.fit.sphere_kalman) in its information form:
rows absorbed, the least-squares state, and its centre and radius in mm."""
from __future__ import annotations

import numpy as np
from numba import njit

from models.fit.small_linalg import cholesky


@njit(cache=True)
def add_sphere_rows(Y, y, P, p0, scale):
    """The sphere filter's information form, in place: Y (4, 4) += sum h h^T, y (4,) +=
    sum h |x|^2 over the points P (N, 3) mm in scaled coordinates x = (p - p0) / scale,
    h = [2x, 2y, 2z, 1]."""
    for n in range(P.shape[0]):
        x0, x1, x2 = (P[n, 0] - p0[0]) / scale, (P[n, 1] - p0[1]) / scale, (P[n, 2] - p0[2]) / scale
        h = np.array([2.0 * x0, 2.0 * x1, 2.0 * x2, 1.0])
        r2 = x0 * x0 + x1 * x1 + x2 * x2
        for i in range(4):
            y[i] += h[i] * r2
            for j in range(4):
                Y[i, j] += h[i] * h[j]


@njit(cache=True)
def sphere_state(Y, y):
    """(state [cx, cy, cz, r^2 - |c|^2] (4,), ok): the least-squares solution Y^-1 y; not ok
    when Y is not positive definite (coplanar points) or the radius is not real."""
    L, ok = cholesky(Y)
    x = np.zeros(4)
    if not ok:
        return x, False
    u = np.zeros(4)
    for i in range(4):
        acc = 0.0
        for k in range(i):
            acc += L[i, k] * u[k]
        u[i] = (y[i] - acc) / L[i, i]
    for i in range(3, -1, -1):
        acc = 0.0
        for k in range(i + 1, 4):
            acc += L[k, i] * x[k]
        x[i] = (u[i] - acc) / L[i, i]
    return x, x[3] + x[0] * x[0] + x[1] * x[1] + x[2] * x[2] > 0.0


@njit(cache=True)
def sphere_absorb(Y, y, P, p0, scale, n_total):
    """add_sphere_rows, then (state (4,), ok) of sphere_state once the filter holds
    n_total >= 4 points (not ok before: fewer than four points define no sphere)."""
    add_sphere_rows(Y, y, P, p0, scale)
    if n_total < 4:
        return np.zeros(4), False
    return sphere_state(Y, y)


@njit(cache=True)
def sphere_center_radius(state, p0, scale, center):
    """Radius (mm) of the sphere filter's state [c, r^2 - |c|^2] (coordinates (x - p0) /
    scale); its centre (mm, frame of p0) is written to center (3,)."""
    cx, cy, cz, k = state[0], state[1], state[2], state[3]
    center[0], center[1], center[2] = p0[0] + scale * cx, p0[1] + scale * cy, p0[2] + scale * cz
    return scale * np.sqrt(k + cx * cx + cy * cy + cz * cz)

