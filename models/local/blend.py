"""The local field's blend (models.local.field_kernels): the nodes near a direction and
their quadratics averaged there, at several directions in one pass over the nodes.

A point's distance takes the blend at its direction and at two directions 1e-5 rad
beside it (the gradient's forward differences), and the barrier's bound at four more
around it (field_kernels.lateral_bound); all of them read the same candidate nodes. One
pass over those nodes does each node's own work once (its tangent frame, its angle from
the data, a node without data's variance) and the directions' work per direction, with
each direction's sums taken in the nodes' order as one direction's pass would take them:
the same numbers as blending the directions one by one, for less of the work.
Radii mm from the fixed centre c0; directions unit vectors; angles rad.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models.local.geometry import band, global_radius, node_frame, small_angle, wendland
from models.local.kernels import global_sd

MAX_CANDIDATES = 256  # nodes a blend may read (blend_deg / spacing_deg <= 4: about 60; lateral_bound's 1.75 blends: 185)
N_SUMS = 8  # blend_many's sums per direction: sw, sr, ss, sW, sWr, sWrr, sWa, and the global radius (NaN: not yet)


@njit(cache=True, inline="always")
def candidates(dirs, u0, u1, u2, angle, cand):
    """The number of nodes within `angle` rad of the unit direction u, their indices
    written to cand (as many as it holds)."""
    k0, k1 = band(dirs.shape[0], u2, 2.0 * np.sin(0.5 * angle))
    cos_a = np.cos(angle)
    nc = 0
    for k in range(k0, k1):
        if u0 * dirs[k, 0] + u1 * dirs[k, 1] + u2 * dirs[k, 2] > cos_a and nc < cand.shape[0]:
            cand[nc] = k
            nc += 1
    return nc


@njit(cache=True, inline="always")
def blend_many(W, D, dirs, blend, c0, gp, x, cov, excess, has, near, prior, cand, nc, sums, out):
    """out[i] = (radius mm, sd mm, gap rad) of the field at each unit direction W[i], i < D:
    the nodes cand[:nc] within `blend` rad of it (their quadratics; at nodes without data
    the trend quadric's quadratic where departures.fill_trend put one, else the global
    radius) averaged with Wendland's weight over each one's variance there (a node
    extrapolating across its data counts little); the sd their standard deviations with the
    same weights and the spread of their radii about that mean in Wendland's weights alone
    (the variance of a mixture: a confident node must not hide the others' disagreement);
    the gap the nodes' angles from the nearest data in Wendland's weights (smooth over
    directions: what the sd's calibration is indexed by, field_kernels.calibrated_sd). The sd
    is the uncalibrated one. `sums` (>= D, N_SUMS): a workspace."""
    cos_b = np.cos(blend)
    floor2 = prior[5] * prior[5]  # the floor: what the quadratics' spread near data leaves unexplained
    for i in range(D):
        for s in range(N_SUMS - 1):
            sums[i, s] = 0.0
        sums[i, N_SUMS - 1] = np.nan
    for j in range(nc):
        k = cand[j]
        d0, d1, d2 = dirs[k, 0], dirs[k, 1], dirs[k, 2]
        fitted = has[k] != 0.0
        quadratic = fitted or x[k, 0] > 0.0  # fitted, or the trend's (departures.fill_trend)
        framed = False
        e10 = e11 = e12 = e20 = e21 = e22 = 0.0
        gap_k = small_angle(near[k])
        v_free = 0.0  # a node without data: the global model's variance at its gap, and its departures'
        if not fitted:
            sd = global_sd(gap_k, prior)
            v_free = sd * sd + excess[k]  # (spread_departures)
        for i in range(D):
            u0, u1, u2 = W[i, 0], W[i, 1], W[i, 2]
            c = u0 * d0 + u1 * d1 + u2 * d2
            if c <= cos_b:
                continue
            w = wendland(small_angle(c) / blend)
            if w <= 0.0:
                continue
            r = 0.0
            p1 = p2 = p3 = p4 = p5 = 0.0
            if quadratic:
                if not framed:
                    e10, e11, e12, e20, e21, e22 = node_frame(d0, d1, d2)
                    framed = True
                t1 = (u0 * e10 + u1 * e11 + u2 * e12) / c
                t2 = (u0 * e20 + u1 * e21 + u2 * e22) / c
                p1, p2, p3, p4, p5 = t1, t2, t1 * t1, t1 * t2, t2 * t2
                r = x[k, 0] + x[k, 1] * p1 + x[k, 2] * p2 + x[k, 3] * p3 + x[k, 4] * p4 + x[k, 5] * p5
            if fitted:
                C = cov[k]
                v = (C[0] + 2.0 * (C[1] * p1 + C[2] * p2 + C[3] * p3 + C[4] * p4 + C[5] * p5)
                     + C[6] * p1 * p1 + 2.0 * (C[7] * p1 * p2 + C[8] * p1 * p3 + C[9] * p1 * p4 + C[10] * p1 * p5)
                     + C[11] * p2 * p2 + 2.0 * (C[12] * p2 * p3 + C[13] * p2 * p4 + C[14] * p2 * p5)
                     + C[15] * p3 * p3 + 2.0 * (C[16] * p3 * p4 + C[17] * p3 * p5)
                     + C[18] * p4 * p4 + 2.0 * C[19] * p4 * p5 + C[20] * p5 * p5) + excess[k]
            else:
                if not quadratic:
                    if sums[i, 7] != sums[i, 7]:
                        sums[i, 7] = global_radius(c0, gp, u0, u1, u2)
                    r = sums[i, 7]
                v = v_free
            v += floor2
            sums[i, 6] += w * gap_k
            sums[i, 3] += w  # the nodes' spread about the mean in their plain Wendland weights (a confident node
            sums[i, 4] += w * r  # that extrapolates must not hide the others' disagreement)
            sums[i, 5] += w * r * r
            w /= v
            sums[i, 0] += w
            sums[i, 1] += w * r
            sums[i, 2] += w * np.sqrt(v)
    for i in range(D):
        sw, sW = sums[i, 0], sums[i, 3]
        if sw <= 0.0:
            out[i, 0], out[i, 1], out[i, 2] = global_radius(c0, gp, W[i, 0], W[i, 1], W[i, 2]), prior[2], np.pi
            continue
        rm = sums[i, 1] / sw
        spread = max((sums[i, 5] - 2.0 * rm * sums[i, 4]) / sW + rm * rm, 0.0)  # the nodes' disagreement about the mean
        sd = sums[i, 2] / sw
        out[i, 0], out[i, 1], out[i, 2] = rm, np.sqrt(sd * sd + spread), sums[i, 6] / sW
