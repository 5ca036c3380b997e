"""Compiled kernel of the scan range (models.adaptive.scan_range): the exact diameter of a
growing point set, updated by blocks with bounding balls."""
from __future__ import annotations

import numpy as np
from numba import njit

SCAN_BLOCK = 16  # points per bounding ball of models.adaptive.scan_range (16: ~1 us per point on the paper spiral, 64: ~2.5)


@njit(cache=True)
def diameter_after_adding(X, block_r, n, P, p0, diameter):
    """The diameter (mm) of the first n rows of X (cap, 3) and the rows x = p - p0 of the
    points P (k, 3) mm, given theirs (`diameter`); the x are stored as rows n.. n + k - 1
    and their blocks updated, in place. Block b holds rows [b B, (b + 1) B) with B =
    SCAN_BLOCK, its ball centred on row b B with radius block_r[b]. A block is skipped for
    the whole batch when the new points' ball (about the first, radius rho) cannot reach
    past the largest distance so far: |x_0 - centre| + rho + radius <= `diameter`; the
    others are skipped per point as |x - centre| + radius <= the largest distance found
    so far. The new points are compared with each other directly."""
    k = P.shape[0]
    for i in range(k):
        X[n + i, 0], X[n + i, 1], X[n + i, 2] = P[i, 0] - p0[0], P[i, 1] - p0[1], P[i, 2] - p0[2]
    m0, m1, m2 = X[n, 0], X[n, 1], X[n, 2]
    rho = 0.0
    for i in range(1, k):
        rho = max(rho, np.sqrt((X[n + i, 0] - m0) ** 2 + (X[n + i, 1] - m1) ** 2 + (X[n + i, 2] - m2) ** 2))
    n_blocks = (n + SCAN_BLOCK - 1) // SCAN_BLOCK
    batch = k > 1  # one point (an A-scan): its per-point test below is this one, no pre-pass
    candidates = np.empty(n_blocks if batch else 0, np.int64)
    n_cand = 0 if batch else n_blocks
    for b in range(n_blocks if batch else 0):
        c = b * SCAN_BLOCK
        slack = diameter - block_r[b] - rho
        if not (slack >= 0.0 and (m0 - X[c, 0]) ** 2 + (m1 - X[c, 1]) ** 2 + (m2 - X[c, 2]) ** 2 <= slack * slack):
            candidates[n_cand] = b
            n_cand += 1
    best, best2 = diameter, diameter * diameter
    for i in range(k):
        x0, x1, x2 = X[n + i, 0], X[n + i, 1], X[n + i, 2]
        for q in range(n_cand):
            b = candidates[q] if batch else q
            c = b * SCAN_BLOCK
            slack = best - block_r[b]  # |x - centre| + radius <= best, without a square root
            if slack >= 0.0 and (x0 - X[c, 0]) ** 2 + (x1 - X[c, 1]) ** 2 + (x2 - X[c, 2]) ** 2 <= slack * slack:
                continue
            for j in range(c, min(n, c + SCAN_BLOCK)):
                d2 = (x0 - X[j, 0]) ** 2 + (x1 - X[j, 1]) ** 2 + (x2 - X[j, 2]) ** 2
                if d2 > best2:
                    best2 = d2
        for j in range(n, n + i):
            d2 = (x0 - X[j, 0]) ** 2 + (x1 - X[j, 1]) ** 2 + (x2 - X[j, 2]) ** 2
            if d2 > best2:
                best2 = d2
        best = np.sqrt(best2)
    for j in range(n, n + k):
        b = j // SCAN_BLOCK
        if j % SCAN_BLOCK == 0:
            block_r[b] = 0.0
        else:
            c = b * SCAN_BLOCK
            r = np.sqrt((X[j, 0] - X[c, 0]) ** 2 + (X[j, 1] - X[c, 1]) ** 2 + (X[j, 2] - X[c, 2]) ** 2)
            if r > block_r[b]:
                block_r[b] = r
    return np.sqrt(best2)

