"""Compiled distances of points from a quadric v (10,) in the fits' scaled coordinates
(models.fit.ellipsoid_fit): Taubin's RMS residual from a scatter matrix, Sampson's
first-order distance per point."""
from __future__ import annotations

import numpy as np
from numba import njit


# dQ/dx = 2(a x + h y + g z + p), dQ/dy = 2(h x + b y + f z + q), dQ/dz = 2(g x + f y + c z + r):
# row i lists the coefficients of v multiplying [x, y, z, 1] in component i.
GRAD_ROWS = np.array([[0, 5, 4, 6], [5, 1, 3, 7], [4, 3, 2, 8]])


@njit(cache=True)
def taubin_residuals(S, V):
    """(k,) RMS point-to-surface distance (scaled units) of each quadric row of V (k, 10)
    over the points of S, in Taubin's first-order form sqrt(v^T S v / sum |grad Q|^2),
    from the moments alone (S[6:, 6:] holds the moments of [2x, 2y, 2z, 1])."""
    M = np.empty((4, 4))
    for i in range(4):
        for j in range(4):
            M[i, j] = S[6 + i, 6 + j] * (0.5 if i < 3 else 1.0) * (0.5 if j < 3 else 1.0)
    out = np.empty(V.shape[0])
    for k in range(V.shape[0]):  # the products by loops, in index order: no temporary arrays
        q2 = 0.0
        for i in range(10):
            Sv = 0.0
            for j in range(10):
                Sv += S[i, j] * V[k, j]
            q2 += V[k, i] * Sv
        g2 = 0.0
        for i in range(3):
            wMw = 0.0
            for a in range(4):
                Mw = 0.0
                for b in range(4):
                    Mw += M[a, b] * V[k, GRAD_ROWS[i, b]]
                wMw += V[k, GRAD_ROWS[i, a]] * Mw
            g2 += wMw
        g2 *= 4.0
        out[k] = np.sqrt(max(q2, 0.0) / g2) if g2 > 0.0 else np.inf
    return out


@njit(cache=True)
def residuals_since(S, S_old, v1, v2):
    """(e1, e2): taubin_residuals of the quadrics v1 and v2 (10,) over the points added to a
    scatter matrix since it was S_old (S - S_old), in one compiled call (a checkpoint's
    prequential errors: models.adaptive.transition)."""
    V = np.empty((2, 10))
    V[0, :] = v1
    V[1, :] = v2
    e = taubin_residuals(S - S_old, V)
    return e[0], e[1]


@njit(cache=True, inline="always")
def half_gradient(v, x, y, z):
    """grad Q / 2 at the point (x, y, z) (scaled coordinates) of the quadric v (10,), as
    three floats."""
    return (v[0] * x + v[5] * y + v[4] * z + v[6], v[5] * x + v[1] * y + v[3] * z + v[7],
            v[4] * x + v[3] * y + v[2] * z + v[8])


@njit(cache=True)
def sampson_one(v, x, y, z):
    """|Q| / |grad Q| of the point (x, y, z) (scaled coordinates) from the quadric v (10,):
    Sampson's first-order distance (scaled units; inf where the gradient vanishes)."""
    a, b, c, f, g, h, p, q, r, d = v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], v[8], v[9]
    Q = a * x * x + b * y * y + c * z * z + 2.0 * (f * y * z + g * x * z + h * x * y + p * x + q * y + r * z) + d
    gx, gy, gz = half_gradient(v, x, y, z)
    grad = 2.0 * np.sqrt(gx * gx + gy * gy + gz * gz)
    return abs(Q) / grad if grad > 0.0 else np.inf


@njit(cache=True)
def sampson_distances(v, X):
    """(K,) sampson_one of each row of X (K, 3) (scaled coordinates) from the quadric v (10,)."""
    out = np.empty(X.shape[0])
    for k in range(X.shape[0]):
        out[k] = sampson_one(v, X[k, 0], X[k, 1], X[k, 2])
    return out

