"""Compiled kernels of the local retina model (models.local.grid): the per-node weighted
least squares that points update and the node solve with the global prior (the
geometry they share: models.local.geometry; the departures from the global quadric:
models.local.departures; the blended field: models.local.field_kernels).

Radii are mm from the fixed model centre c0; directions unit vectors; angles rad.
Node k of an n-node grid has direction dirs[k] = fibonacci_directions(n)[k]
(models.adaptive.coverage: z falls with k, so a z band is an index range) and a tangent
frame (e1, e2) made from it alone (geometry.node_frame).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models.fit.small_linalg import cholesky_into
from models.local.departures import SLOPE_UNDERSTATEMENT, gathered_departure, node_departure
from models.local.geometry import (ELLIPSOID, GLOBAL_SIZE, N_BASIS, SPHERE, band, global_radius, node_frame,
                                   quadric_taylor, small_angle, wendland)

WORKSPACE = 159  # solve_node's small arrays: R 9, m, pinv, A m 6 each, rhs, y, z 6 each, M, L, L^-1 36 each, the
# global's quadratic 6

@njit(cache=True)
def absorb_points(P, B, c0, gp, gate, dirs, support, track, A, b, rr, wsum, near, listed, dirty, n_dirty, solved_w,
                  growth, last, sample_mm):
    """Add the finite points P (M, 3) mm to the nodes of an n-node grid within `support`
    rad of their direction from c0: per node the weighted normal equations of the local
    quadratic in gnomonic coordinates (A (n, 6, 6) upper triangle, b (n, 6), rr (n,) sum
    w r^2, wsum (n,) sum w; w Wendland's weight of angle / support); the cosine of the
    nearest data angle (near (n,)) of the nodes within `track` rad. A node whose data changed is
    appended to dirty once (listed (n,) bool marks it until it is solved) when its weight
    exceeds (1 + growth) x its weight at its last solve (solved_w; a node solved on 100
    points barely moves with the 101st: consecutive A-scans touch the same nodes). Each
    point's weights are scaled by its share of a sample: its lateral step from the previous
    taken point over sample_mm, at most 1 (a still beam adds nothing;
    LocalConfig.sample_length_mm). With the beams' directions B (M, 3; normalised here; a row
    not finite or shorter than 0.5 takes the rule without beams) the step is measured
    across the point's beam (the step less its component along the beam: an
    A-scan's noise lies along its beam and drops out); without them (B of 0 rows) it is the
    radius x the chord between the point's direction from c0 and the previous one's, which
    the noise of an oblique beam lengthens. last (5,): the previous taken point's position
    (3,) mm, 1 once there is one, and the shares' running sum; updated in place. A point whose
    radius lies outside [gate[0], gate[1]] mm, or further than gate[2] mm from the global
    quadric gp along its direction (when gp[0] != 0), is skipped: no retina of the
    population lies there. Returns (new n_dirty, points taken)."""
    chord_t = 2.0 * np.sin(0.5 * track)
    cos_s, cos_t = np.cos(support), np.cos(track)
    phi = np.empty(N_BASIS)
    taken = 0
    beams = B.shape[0] == P.shape[0] and B.shape[0] > 0
    for i in range(P.shape[0]):
        v0, v1, v2 = P[i, 0] - c0[0], P[i, 1] - c0[1], P[i, 2] - c0[2]
        r = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        if not (np.isfinite(r) and r > 1e-9):
            continue
        u0, u1, u2 = v0 / r, v1 / r, v2 / r
        if not gate[0] <= r <= gate[1]:
            continue
        if gp[0] != 0.0 and not abs(r - global_radius(c0, gp, u0, u1, u2)) <= gate[2]:
            continue
        taken += 1
        if last[3] == 0.0:
            share = 1.0
        elif beams and 0.25 < B[i, 0] * B[i, 0] + B[i, 1] * B[i, 1] + B[i, 2] * B[i, 2] < np.inf:  # finite, not degenerate
            nb = np.sqrt(B[i, 0] * B[i, 0] + B[i, 1] * B[i, 1] + B[i, 2] * B[i, 2])
            b0, b1, b2 = B[i, 0] / nb, B[i, 1] / nb, B[i, 2] / nb
            s0, s1, s2 = P[i, 0] - last[0], P[i, 1] - last[1], P[i, 2] - last[2]
            along = s0 * b0 + s1 * b1 + s2 * b2
            s0, s1, s2 = s0 - along * b0, s1 - along * b1, s2 - along * b2
            share = min(np.sqrt(s0 * s0 + s1 * s1 + s2 * s2) / sample_mm, 1.0)
        else:  # the previous point's direction from c0, computed as this point's is
            w0, w1, w2 = last[0] - c0[0], last[1] - c0[1], last[2] - c0[2]
            rl = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            g0, g1, g2 = u0 - w0 / rl, u1 - w1 / rl, u2 - w2 / rl
            share = min(r * np.sqrt(g0 * g0 + g1 * g1 + g2 * g2) / sample_mm, 1.0)
        last[0], last[1], last[2], last[3] = P[i, 0], P[i, 1], P[i, 2], 1.0
        last[4] += share
        k0, k1 = band(dirs.shape[0], u2, chord_t)
        for k in range(k0, k1):
            d0, d1, d2 = dirs[k, 0], dirs[k, 1], dirs[k, 2]
            c = u0 * d0 + u1 * d1 + u2 * d2
            if c < cos_t:
                continue
            if c > near[k]:
                near[k] = c
            if c < cos_s:
                continue
            w = share * wendland(small_angle(c) / support)
            if w <= 0.0:
                continue
            e10, e11, e12, e20, e21, e22 = node_frame(d0, d1, d2)
            t1 = (u0 * e10 + u1 * e11 + u2 * e12) / c
            t2 = (u0 * e20 + u1 * e21 + u2 * e22) / c
            phi[0], phi[1], phi[2], phi[3], phi[4], phi[5] = 1.0, t1, t2, t1 * t1, t1 * t2, t2 * t2
            for a in range(N_BASIS):
                wa = w * phi[a]
                b[k, a] += wa * r
                for c_ in range(a, N_BASIS):
                    A[k, a, c_] += wa * phi[c_]
            rr[k] += w * r * r
            wsum[k] += w
            if not listed[k] and wsum[k] > (1.0 + growth) * solved_w[k]:
                listed[k] = True
                dirty[n_dirty] = k
                n_dirty += 1
    return n_dirty, taken


@njit(cache=True)
def solve_node(k, dirs, c0, gp, tp, A, b, rr, wsum, near, prior, reach, nb_off, nb_idx, nb_ang, has, dev, slope, x, cov,
               excess, ws):
    """Node k's posterior: the local quadratic x[k] (6,) (mm, mm/rad, mm/rad^2), its
    covariance cov[k] (N_COV,: the upper triangle row by row, mm^2 per basis products),
    the misfit variance excess[k] (mm^2) and the slope of its departure from the global
    quadric, slope[k] (2,) (mm/rad along the node's e1, e2: SLOPE_UNDERSTATEMENT x the
    fitted slopes less the global's). Data: the weighted normal equations
    (A, b, rr, wsum) with noise prior[0] mm; prior: the Taylor expansion at the node of
    the trend quadric tp, or of the global quadric gp without one (tp[0] == 0;
    geometry.quadric_taylor); the
    correction to it (its first prior[6] terms, the rest 0) has the standard deviations
    of a smooth random field's value, slopes and curvatures, s, s / l and sqrt(3) s_c / l^2
    (Rasmussen & Williams 2006, 9.4; length scale l = prior[4] rad), with s_g =
    global_sd(angle of near[k]) (prior[1] near data growing to prior[2] at prior[3] rad
    from it), s^2 = s_g^2 + the departure variance of node k and of its neighbours within
    `reach` rad that hold data (gathered_departure over neighbour_table's rows;
    dev[k], node k's own departure, set first) and s_c^2 = s_g^2 + node k's own departure^2
    (when over the departure floor prior[7]): where the data nearby depart from the global quadric
    by D, the correction's offset and tilt are that uncertain (a detachment's flank is a
    tilt at a node's scale), and where the node's own data depart, its curvature too (the
    top of a detachment 3.5 mm high bends more than the global model's curvature prior
    allows; loosening the curvature of every node near a departure bends the quadratics
    between scan lines: the scanned p95 on the staphyloma's spiral beams 303 -> 377 um).
    The variance is the posterior's, scaled by the weighted mean square residual over the
    noise's (the Birge ratio, when > 1); the excess is
    that residual's excess over the noise: a quadratic that does not follow the retina
    within the support says so. ws: a workspace (WORKSPACE,) the solve's small arrays live in
    (one allocation per solve_nodes call, not ten per node: a third of a node's solve time)."""
    nf = int(prior[6])  # the correction's fitted terms: 1 (a height), 3 (and its slopes) or 6 (and curvatures)
    R = ws[0:9].reshape((3, 3))
    m, pinv, Am = ws[9:15], ws[15:21], ws[21:27]
    rhs, y, z = ws[27:27 + nf], ws[33:33 + nf], ws[39:39 + nf]
    M = ws[45:45 + nf * nf].reshape((nf, nf))
    L = ws[81:81 + nf * nf].reshape((nf, nf))
    Li = ws[117:117 + nf * nf].reshape((nf, nf))
    mg = ws[153:159]  # the global quadric's quadratic (the departure's slope is from it)
    quadric_taylor(c0, gp, dirs[k, 0], dirs[k, 1], dirs[k, 2], R, mg)
    if tp[0] != 0.0:  # centred on the trend quadric
        quadric_taylor(c0, tp, dirs[k, 0], dirs[k, 1], dirs[k, 2], R, m)
    else:
        m[:] = mg
    noise2 = prior[0] * prior[0]
    dev[k] = node_departure(k, A, b, wsum, mg)
    dep = gathered_departure(k, has, dev, reach, prior[7], nb_off, nb_idx, nb_ang)
    sg = global_sd(np.arccos(min(near[k], 1.0)), prior)
    pinv[0] = 1.0 / (sg * sg + dep)
    ell2 = prior[4] * prior[4]  # the correction's length scale: slopes s / l, curvatures sqrt(3) s_c / l^2
    pinv[1] = pinv[2] = ell2 * pinv[0]
    own = dev[k] * dev[k] if abs(dev[k]) > prior[7] else 0.0
    pinv[3] = pinv[4] = pinv[5] = ell2 * ell2 / (sg * sg + own) / 3.0
    # Am = A m: the global's Taylor expansion's share of the normal equations
    for a in range(N_BASIS):
        s = 0.0
        for c in range(N_BASIS):
            s += (A[k, a, c] if a <= c else A[k, c, a]) * m[c]
        Am[a] = s
    for a in range(nf):
        rhs[a] = (b[k, a] - Am[a]) / noise2
        for c in range(a, nf):
            M[a, c] = M[c, a] = A[k, a, c] / noise2
        M[a, a] += pinv[a]
    x[k, :] = m
    cov[k, :] = 0.0
    excess[k] = 0.0
    slope[k, 0] = slope[k, 1] = 0.0
    ok = cholesky_into(M, L)
    if not ok or not np.isfinite(m[0]):
        cov[k, 0] = 1.0 / pinv[0]
        return
    for a in range(nf):  # L z = rhs, L^T y = z
        s = rhs[a]
        for c in range(a):
            s -= L[a, c] * z[c]
        z[a] = s / L[a, a]
    for a in range(nf - 1, -1, -1):
        s = z[a]
        for c in range(a + 1, nf):
            s -= L[c, a] * y[c]
        y[a] = s / L[a, a]
    Li[:, :] = 0.0  # L^-1 (lower); M^-1 = L^-T L^-1
    for j in range(nf):
        Li[j, j] = 1.0 / L[j, j]
        for a in range(j + 1, nf):
            s = 0.0
            for c in range(j, a):
                s -= L[a, c] * Li[c, j]
            Li[a, j] = s / L[a, a]
    for a in range(nf):
        x[k, a] += y[a]
    slope[k, 0] = SLOPE_UNDERSTATEMENT * (x[k, 1] - mg[1])
    slope[k, 1] = SLOPE_UNDERSTATEMENT * (x[k, 2] - mg[2])
    ss = rr[k]  # weighted residual sum of squares of x over the node's data
    for a in range(N_BASIS):
        ss -= 2.0 * x[k, a] * b[k, a]
        for c in range(N_BASIS):
            ss += x[k, a] * x[k, c] * (A[k, a, c] if a <= c else A[k, c, a])
    msr = max(ss, 0.0) / wsum[k] if wsum[k] > 0.0 else 0.0
    birge = max(1.0, msr / noise2)
    j = 0
    for a in range(N_BASIS):
        for c in range(a, N_BASIS):
            if c < nf:
                s = 0.0
                for e in range(c, nf):
                    s += Li[e, a] * Li[e, c]
                cov[k, j] = birge * s
            j += 1
    excess[k] = max(msr - noise2, 0.0)


@njit(cache=True, inline="always")
def global_sd(angle, prior):
    """The global model's standard deviation (mm) at `angle` rad from the nearest data:
    prior[1] at the data, growing linearly to prior[2] at prior[3] rad and beyond."""
    t = min(angle / prior[3], 1.0)
    return prior[1] + (prior[2] - prior[1]) * t


@njit(cache=True)
def solve_nodes(nodes, count, dirs, c0, gp, tp, A, b, rr, wsum, near, prior, reach, nb_off, nb_idx, nb_ang, dev, slope, x,
                cov, excess, has, listed, solved_w):
    """Solve the first `count` nodes listed in `nodes` (solve_node), mark them as holding
    data (has) and no longer listed, their weight then in solved_w."""
    ws = np.empty(WORKSPACE)
    for j in range(count):
        k = nodes[j]
        solve_node(k, dirs, c0, gp, tp, A, b, rr, wsum, near, prior, reach, nb_off, nb_idx, nb_ang, has, dev, slope, x, cov,
                   excess, ws)
        has[k] = 1.0
        listed[k] = False
        solved_w[k] = wsum[k]


_IDENTITY = np.eye(3).ravel()


def global_params(shape) -> np.ndarray:
    """The kernels' (GLOBAL_SIZE,) packing of a models.Sphere or Ellipsoid."""
    gp = np.zeros(GLOBAL_SIZE)
    if hasattr(shape, "radii"):
        gp[0], gp[1:4], gp[4:13], gp[13:16] = ELLIPSOID, shape.center, np.asarray(shape.rotation).ravel(), shape.radii
    else:
        gp[0], gp[1:4], gp[4:13], gp[13] = SPHERE, shape.center, _IDENTITY, shape.radius
    return gp
