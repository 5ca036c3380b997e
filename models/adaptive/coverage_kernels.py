"""Compiled kernels of the direction coverage (models.adaptive.coverage): the nearest bin of
a direction on a Fibonacci sphere, bins marked by measured points, the covered rows, the
nearest covered direction and the largest misfit near a direction, and depths inside a
model shape. Units: mm; directions unit vectors in the frame of the points."""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def inside_depth(L, radii, r_max):
    """(M,) per row of L (M, 3): max(r_max - |L_m|, 0) without `radii`, max(r_max (1 -
    |L_m / radii|), 0) with them (3 floats) (NaN stays NaN: np.maximum's), |x| as
    np.linalg.norm computes it: sqrt((x0^2 + x1^2) + x2^2)."""
    out = np.empty(L.shape[0])
    for m in range(L.shape[0]):
        x0, x1, x2 = L[m, 0], L[m, 1], L[m, 2]
        if radii is None:
            v = r_max - np.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        else:
            x0, x1, x2 = x0 / radii[0], x1 / radii[1], x2 / radii[2]
            v = r_max * (1.0 - np.sqrt(x0 * x0 + x1 * x1 + x2 * x2))
        out[m] = v if v >= 0.0 or v != v else 0.0
    return out


@njit(cache=True)
def nearest_and_worst(V, dirs, misfit, cos_angle, chord=2.0):
    """Per unit row of V (M, 3): the largest cosine to any of `dirs` (N, 3) (-2 without
    any), and the largest `misfit` (N,) among the dirs with cosine >= cos_angle (0 if none).
    A scan of the covered directions: for the loop's few points per step, cheaper than a
    k-d tree's per-query overhead, and exact. With `dirs` sorted by z, only those within
    `chord` of the row in z are scanned (a direction at angle a lies 2 sin(a / 2) or less
    away, in z too): then the cosine is exact where it is at least 1 - chord^2 / 2, and
    below that where it is not (2.0: every direction)."""
    M, N = V.shape[0], dirs.shape[0]
    best = np.full(M, -2.0)
    worst = np.zeros(M)
    for m in range(M):
        a0, a1, a2 = V[m, 0], V[m, 1], V[m, 2]
        j0 = np.searchsorted(dirs[:, 2], a2 - chord) if chord < 2.0 else 0
        j1 = np.searchsorted(dirs[:, 2], a2 + chord, side="right") if chord < 2.0 else N
        b, w = -2.0, 0.0
        for j in range(j0, j1):
            c = a0 * dirs[j, 0] + a1 * dirs[j, 1] + a2 * dirs[j, 2]
            if c > b:
                b = c
            if c >= cos_angle and misfit[j] > w:
                w = misfit[j]
        best[m], worst[m] = b, w
    return best, worst


@njit(cache=True, inline="always")
def _closer(dirs, k, u0, u1, u2, best, best_d):
    """(best, best_d, dz): row k of `dirs` replaces the best row so far (squared distance
    best_d to the direction (u0, u1, u2)) when nearer, or as near with a smaller index;
    dz its z offset from the direction."""
    d0, d1, d2 = dirs[k, 0] - u0, dirs[k, 1] - u1, dirs[k, 2] - u2
    d = d0 * d0 + d1 * d1 + d2 * d2
    if d < best_d or (d == best_d and k < best):
        return k, d, d2
    return best, best_d, d2


@njit(cache=True)
def nearest_fibonacci(u0, u1, u2, dirs, hint=-1):
    """Index of the row of `dirs` (n, 3), fibonacci_directions(n), nearest (Euclidean) to
    the direction (u0, u1, u2) (of equally near rows the first): an exact search over the
    rows sorted by z. The rows' z = 1 - 2 (k + 1/2) / n fall with k, and a row whose z
    differs from u2 by more than the best distance so far cannot be nearer. Given a
    `hint`, a row near the direction (the bin of the A-scan before), one pass compares
    every row whose z lies within the hint's distance; without one, the scan widens from
    the row of nearest z until both sides are past the bound (a few hundred rows for 2
    deg bins)."""
    n = dirs.shape[0]
    if hint >= 0:
        best = hint
        d0, d1, d2 = dirs[hint, 0] - u0, dirs[hint, 1] - u1, dirs[hint, 2] - u2
        best_d = d0 * d0 + d1 * d1 + d2 * d2
        r = np.sqrt(best_d)
        # the rows with z in [u2 - r, u2 + r], and two more on each side for rounding
        lo = max(int(0.5 * n * (1.0 - (u2 + r)) - 0.5) - 2, 0)
        hi = min(int(0.5 * n * (1.0 - (u2 - r)) - 0.5) + 3, n)
        for k in range(lo, hi):
            best, best_d, _ = _closer(dirs, k, u0, u1, u2, best, best_d)
        return best
    k0 = min(max(int(round(0.5 * n * (1.0 - u2) - 0.5)), 0), n - 1)
    best, best_d = k0, np.inf
    lo, hi = k0, k0 + 1  # next rows to visit below (decreasing k) and above
    while lo >= 0 or hi < n:
        if lo >= 0:
            best, best_d, dz = _closer(dirs, lo, u0, u1, u2, best, best_d)
            lo = lo - 1 if dz * dz <= best_d else -1
        if hi < n:
            best, best_d, dz = _closer(dirs, hi, u0, u1, u2, best, best_d)
            hi = hi + 1 if dz * dz <= best_d else n
    return best


@njit(cache=True)
def add_points(P, center, dirs, covered, inner, inner_r):
    """Mark the bins (nearest_fibonacci of their direction from `center`) of the finite
    rows of P (N, 3) mm as covered, and keep per bin the point nearest the centre
    (`inner`, its distance `inner_r` mm; of equally near points the last). Returns the
    number of bins newly covered."""
    new = 0
    b = -1
    for i in range(P.shape[0]):
        x, y, z = P[i, 0], P[i, 1], P[i, 2]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            continue
        v0, v1, v2 = x - center[0], y - center[1], z - center[2]
        r = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        s = max(r, 1e-12)
        b = nearest_fibonacci(v0 / s, v1 / s, v2 / s, dirs, b)  # consecutive A-scans: the last bin is near
        if not covered[b]:
            covered[b] = True
            new += 1
        if r <= inner_r[b]:
            inner_r[b] = r
            inner[b, 0], inner[b, 1], inner[b, 2] = x, y, z
    return new


@njit(cache=True)
def covered_rows(covered, dirs, inner, m):
    """The rows of `dirs` and `inner` (n, 3) of the m covered bins, the last bin first: by
    z ascending, as a CoverageView holds them (fibonacci_directions' z falls with the bin)."""
    D, I = np.empty((m, 3)), np.empty((m, 3))
    j = 0
    for b in range(covered.shape[0] - 1, -1, -1):
        if j == m:
            break
        if covered[b]:
            D[j, 0], D[j, 1], D[j, 2] = dirs[b, 0], dirs[b, 1], dirs[b, 2]
            I[j, 0], I[j, 1], I[j, 2] = inner[b, 0], inner[b, 1], inner[b, 2]
            j += 1
    return D, I
