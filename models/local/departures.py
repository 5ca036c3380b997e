"""The departures of the retina from the global quadric in the local model (compiled):
each node's measured departure, how far it says the retina may depart where the data do
not reach (the prior of the nodes' offset and tilt: departure_variance; the standard
deviation past the data's edge: unseen_departure_variance), and the neighbour table the
gathers read. Units: mm, rad; grids and arrays as in models.local.kernels.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models.local.geometry import N_BASIS, band, quadric_taylor

@njit(cache=True, inline="always")
def node_departure(k, A, b, wsum, mg):
    """The departure (mm) of node k's data from the global quadric: their weighted mean
    residual from it, each datum against the quadric along its own direction (mg (6,) the
    quadric's quadratic at the node, geometry.quadric_taylor: (b[k, 0] - sum_c A[k, 0, c]
    mg[c]) / wsum[k], the data alone). Against the quadric's radius at the node itself, data
    off to one side of it depart by the quadric's slope times their offset (on the
    emmetropic eye's model after bench_closed_loop's 3-turn spiral, its data 6 deg from the
    nodes on average: 37-99 um median, up to 0.27 mm, where the retina departs by nothing)."""
    if not wsum[k] > 0.0:
        return 0.0
    s = b[k, 0]
    for c in range(N_BASIS):
        s -= A[k, 0, c] * mg[c]
    return s / wsum[k]


@njit(cache=True)
def node_departures(nodes, dirs, c0, gp, A, b, wsum, dev):
    """dev[k] = node_departure(k) for the nodes listed (before a pass that solves them all)."""
    R, mg = np.empty((3, 3)), np.empty(N_BASIS)
    for k in nodes:
        quadric_taylor(c0, gp, dirs[k, 0], dirs[k, 1], dirs[k, 2], R, mg)
        dev[k] = node_departure(k, A, b, wsum, mg)


@njit(cache=True, inline="always")
def departure_variance(D, a, reach):
    """D^2 (1 - a / reach) mm^2 (0 beyond `reach` rad): what a departure D mm of the retina
    from the global quadric, measured at a node, says of the retina `a` rad from it (a
    pathology goes on past the data as the data next to it depart, fading over about a
    detachment's or a staphyloma's radius)."""
    return D * D * (1.0 - a / reach) if a < reach else 0.0


# The departure's slope a node's quadratic fits is its mean over the support: at the edge
# of data that stop on a detachment's flank, about half the true slope there (the default
# profile, 2 mm over 25 deg, with the data stopping 15 deg from its centre: 6.6 mm/rad
# fitted against 14.1): slope[k] holds this many times the fitted one.
SLOPE_UNDERSTATEMENT = 2.0


@njit(cache=True, inline="always")
def unseen_departure_variance(D, rise, a, reach):
    """mm^2 (0 beyond `reach` rad): what a departure D mm of the retina from the global
    quadric at a node with data says of the retina `a` rad from it where there is none,
    `rise` mm the departure's linear extrapolation to there from the node's slope: uphill
    (|D + rise| > |D|: towards where the departure grows) (D + rise)^2, a pathology may go
    on rising at the rate the data show, the top of a detachment the scan did not reach
    lying further from the global quadric than its flank; downhill, departure_variance (it
    fades towards the healthy retina). With departure_variance alone: in the closed loop
    with the OCT stream 2.6 ms late (`vitreoguard faults`, class time_offset)
    the boundary held the spiral off the detached eye's top, the data stopped on its flank
    15 deg from its centre, and 0.66 % of the reference samples (that top) lay beyond 3
    sigma on the unsafe side, up to 225 um; with data stopping at 0.75-0.85 of a
    detachment's radius, 30-48 % of its top did, up to 2.6 mm (tests/models/local)."""
    if a >= reach:
        return 0.0
    up = D + rise
    return up * up if abs(up) > abs(D) else departure_variance(D, a, reach)


@njit(cache=True)
def gathered_departure(k, has, dev, reach, floor, nb_off, nb_idx, nb_ang):
    """The largest departure_variance (mm^2) at node k over node k and its neighbours j
    within `reach` rad (nb_idx[nb_off[k]:nb_off[k + 1]] at the angles nb_ang: neighbour_table)
    that hold data and whose departure |dev[j]| > floor mm."""
    best = dev[k] * dev[k] if abs(dev[k]) > floor else 0.0
    for i in range(nb_off[k], nb_off[k + 1]):
        j = nb_idx[i]
        if has[j] != 0.0 and abs(dev[j]) > floor:
            best = max(best, departure_variance(dev[j], nb_ang[i], reach))
    return best


@njit(cache=True)
def neighbour_table(dirs, reach):
    """(off (n + 1,), idx, ang): the nodes within `reach` rad of node k, itself excluded,
    are idx[off[k]:off[k + 1]], at the angles ang[off[k]:off[k + 1]] rad (compressed rows,
    built once per grid: a gather then reads the ~200 nodes of a 25 deg disc instead of
    scanning the ~2,000 of its z band, and no angle)."""
    n = dirs.shape[0]
    chord, cos_r = 2.0 * np.sin(0.5 * reach), np.cos(reach)
    off = np.zeros(n + 1, dtype=np.int64)
    for sweep in range(2):
        idx = np.empty(off[n] if sweep else 0, dtype=np.int64)
        ang = np.empty(off[n] if sweep else 0)
        for k in range(n):
            m = off[k]
            k0, k1 = band(n, dirs[k, 2], chord)
            for j in range(k0, k1):
                c = dirs[k, 0] * dirs[j, 0] + dirs[k, 1] * dirs[j, 1] + dirs[k, 2] * dirs[j, 2]
                if j != k and c > cos_r:
                    if sweep:
                        idx[m], ang[m] = j, np.arccos(min(c, 1.0))
                        m += 1
                    else:
                        off[k + 1] += 1
        if not sweep:
            for k in range(n):
                off[k + 1] += off[k]
    return off, idx, ang


# A node's data are faint where its nearest datum lies beyond this fraction of the support:
# Wendland's weight there is under 1.6 % of a datum's at the node, and the prior holds the
# node's quadratic near the global quadric (spread_departures). With a 12 deg support and
# only the edge rule, 2.6 % of a detachment's unscanned top (data stopping 0.85 of its radius
# from its centre, 3.5 mm high) lay beyond 3 sigma on the unsafe side, up to 0.43 mm, 8.5-12
# deg from the data (tests/models/local/test_local_model.py).
FAINT_SUPPORT = 0.75


@njit(cache=True)
def spread_departures(dirs, frames, x, has, excess, dev, slope, near, edge, faint, reach, floor, cross, nb_off, nb_idx,
                      nb_ang, nx_off, nx_idx, nx_ang, out):
    """out (n,) mm^2: a node's variance beyond its quadratic's posterior.

    A node with data j: its excess plus the largest squared error of its quadratic at the
    nodes with data k within `cross` rad, against their own value x[k, 0] (how wrong its
    extrapolation is where the data show the retina: at the rim of a detachment a node's
    quadratic from one side misses the other side by as much; on a smooth retina the
    quadratics agree), or, where its nearest datum lies further than `edge` rad (near[j],
    a cosine: one grid spacing; a node at the edge of the data, fitted from their side)
    and it lies uphill of such a node k that departs, (|slope[k]| a_j)^2 at the angle a_j
    to that datum, if larger: its quadratic misses a departure rising past the data at
    that rate by about as much (the edge of a detachment's unscanned top; a departing edge
    node itself too, whichever way the rise goes: its own value is extrapolated that far
    from its data); nearer the data the quadratics follow the rise, and the pointed eye's
    cap, which departs from its sphere everywhere, keeps its sigma between the scan lines:
    36 um median within 2 deg of the data, 58 um with every data node's distance counted).
    A node with data whose nearest datum lies further than `faint` rad (its data weigh
    little: the prior holds its quadratic near the global quadric) takes, besides, what a
    node without data would. A node without data j: the largest unseen_departure_variance of the data nodes k within
    `reach` rad whose departure |dev[k]| > floor mm (dev: the mean residual of a node's data
    from the global quadric, node_departure; slope (n, 2) its rate along the node's frame, both at its
    last solve), with the departure's linear extrapolation from k to j: beyond the edge of
    the data a pathology may go on rising where the data show it rising, and the field reads
    the global quadric there (the same departures loosen every node's prior: solve_node).
    The pairs (k, j) come from two neighbour tables (neighbour_table): (nb_off, nb_idx,
    nb_ang) within at least max(reach, cross) rad for a departing node k, (nx_off, nx_idx,
    nx_ang) within at least `cross` for the others: a departing node's ~215 neighbours
    within 25 deg and another's ~10 within 4.8, not the ~1,900 or ~380 of its z band;
    `frames` (n, 6): geometry.node_frames(dirs)). A pair's rise and quadratic are computed
    only where they count, its angle read from the table."""
    n = dirs.shape[0]
    for k in range(n):
        out[k] = excess[k] if has[k] != 0.0 else 0.0
    cos_x, cos_e, cos_f = np.cos(cross), np.cos(edge), np.cos(faint)
    for k in range(n):
        if has[k] == 0.0:
            continue
        d0, d1, d2 = dirs[k, 0], dirs[k, 1], dirs[k, 2]
        f10, f11, f12, f20, f21, f22 = frames[k, 0], frames[k, 1], frames[k, 2], frames[k, 3], frames[k, 4], frames[k, 5]
        spread = abs(dev[k]) > floor
        within = max(reach, cross) if spread else cross  # the departure's reach only where there is one
        if spread and near[k] < cos_e:  # a departing edge node's own value: extrapolated that far along the rise
            out[k] = max(out[k], excess[k] + (np.hypot(slope[k, 0], slope[k, 1]) * np.arccos(max(near[k], -1.0))) ** 2)
        off, idx, ang = (nb_off, nb_idx, nb_ang) if spread else (nx_off, nx_idx, nx_ang)
        for i in range(off[k], off[k + 1]):  # the neighbours (k itself above)
            a = ang[i]  # arccos of c below, as the table computed it
            if a > within:
                continue
            j = idx[i]
            c = d0 * dirs[j, 0] + d1 * dirs[j, 1] + d2 * dirs[j, 2]
            data = has[j] != 0.0
            faint_j = data and spread and near[j] < cos_f
            close = c > cos_x
            if (data and not faint_j and not close) or not (data or spread):
                continue  # nothing of this pair counts
            rise = 0.0  # the departure's linear extrapolation from node k to node j (gnomonic, k's frame)
            if spread and c > 0.0:
                rise = (slope[k, 0] * (dirs[j, 0] * f10 + dirs[j, 1] * f11 + dirs[j, 2] * f12)
                        + slope[k, 1] * (dirs[j, 0] * f20 + dirs[j, 1] * f21 + dirs[j, 2] * f22)) / c
            if not data:
                out[j] = max(out[j], unseen_departure_variance(dev[k], rise, a, reach))
                continue
            if faint_j:
                out[j] = max(out[j], excess[j] + unseen_departure_variance(dev[k], rise, a, reach))
            if not close:
                continue
            e2 = 0.0
            if spread and near[j] < cos_e and rise * dev[k] > 0.0:  # uphill of k, an edge node
                e2 = (np.hypot(slope[k, 0], slope[k, 1]) * np.arccos(max(near[j], -1.0))) ** 2
            t1 = (d0 * frames[j, 0] + d1 * frames[j, 1] + d2 * frames[j, 2]) / c  # node k's direction, j's gnomonic frame
            t2 = (d0 * frames[j, 3] + d1 * frames[j, 4] + d2 * frames[j, 5]) / c
            e = (x[j, 0] + x[j, 1] * t1 + x[j, 2] * t2 + x[j, 3] * t1 * t1 + x[j, 4] * t1 * t2
                 + x[j, 5] * t2 * t2 - x[k, 0])
            e2 = max(e2, e * e)
            if excess[j] + e2 > out[j]:
                out[j] = excess[j] + e2
    return out


@njit(cache=True)
def fill_trend(dirs, has, near, c0, tp, cos_trend, x):
    """The rows x[k] (6,) of the nodes without data: the trend quadric tp's quadratic at
    the node (quadric_taylor) where the node's nearest data lie within the angle whose
    cosine is `cos_trend` (near[k] > cos_trend) and tp holds c0 (tp[0] != 0), else zeros:
    the field reads a row with x[k, 0] > 0 as the trend there and a zero row as the
    global quadric (models.local.field_kernels)."""
    R = np.empty((3, 3))
    m = np.empty(6)
    for k in range(dirs.shape[0]):
        if has[k] != 0.0:
            continue
        x[k, :] = 0.0
        if tp[0] != 0.0 and near[k] > cos_trend:
            quadric_taylor(c0, tp, dirs[k, 0], dirs[k, 1], dirs[k, 2], R, m)
            if np.isfinite(m).all() and m[0] > 0.0:
                x[k, :] = m
