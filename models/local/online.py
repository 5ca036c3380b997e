"""The local model's online step in one compiled call (models.local.grid.LocalRetinaModel.update):
a packet's points predicted before they are absorbed and the calibration's histograms
(field_kernels.predictions, calibration.absorb_errors), their absorption
(kernels.absorb_points), the record of the nodes that hold data, and the node solves
(kernels.solve_nodes: the nodes the points touched, up to a budget, then a sweep over the
nodes with data in turn), and whether the global quadric holds the model centre. The
same kernels, called from one compiled function instead of one by one from Python: per
A-scan the Python between them and numba's argument checks of five calls were most of
the update's time (measured by `make bench`: the README's results).
Units: mm, rad; arrays as in models.local.kernels.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models.local.calibration import absorb_errors
from models.local.field_kernels import predictions
from models.local.geometry import SPHERE
from models.local.kernels import absorb_points, solve_nodes
from models.shapes.ellipsoid_distance import ellipsoid_distance_and_gradient


@njit(cache=True)
def holds(gp, p, margin):
    """Whether the point p (3,) mm lies at least `margin` mm inside the global quadric gp
    (kernels.global_params' packing): exact (a sphere's distance; an ellipsoid's by
    Eberly's construction unless the ball of its smallest semi-axis already holds p that
    deep)."""
    q0, q1, q2 = p[0] - gp[1], p[1] - gp[2], p[2] - gp[3]
    off = np.sqrt(q0 * q0 + q1 * q1 + q2 * q2)
    if gp[0] == SPHERE:
        return gp[13] - off >= margin
    if min(gp[13], gp[14], gp[15]) - off >= margin:
        return True
    d, _ = ellipsoid_distance_and_gradient(gp[1:4], gp[4:13].reshape((3, 3)), gp[13:16], p.reshape((1, 3)))
    return d[0] >= margin


@njit(cache=True)
def local_step(P, B, c0, gp_old, prior_old, gp, prior, tp, gate, dirs, support, track, blend, growth, budget, sweep,
               reach, nb_off, nb_idx, nb_ang, A, b, rr, wsum, near, listed, dirty, n_dirty, solved_w, data_nodes, n_data,
               in_data, sweep_at, x, cov, excess, extra, has, dev, slope, cal_k, cal_width, hist, count, memory, pred, last,
               sample_mm):
    """One update of the local model by the points P (M, 3) mm, their beams' directions
    B (M, 3) or none (0 rows; kernels.absorb_points). gp_old, prior_old: the
    global quadric and prior the nodes were last solved on (gp_old[0] == 0: none yet; then
    pred is all NaN), which predict P into pred (M, 6) and the calibration's histograms
    (hist, count: |error| / (cal_k sd) in cells cal_width wide, halved past `memory`); gp,
    prior: this update's (gp[0] == 0: none, the points are absorbed and nothing solved);
    tp: the trend quadric the nodes' quadratics are centred on (tp[0] == 0: none, gp's).
    Then up to `budget` of the dirty nodes are solved, the rest moved to the list's front,
    and `sweep` nodes with data from data_nodes[sweep_at] on (their place in the dirty
    list kept). last, sample_mm: the points' shares of a sample (kernels.absorb_points).
    Returns (n_dirty, points taken, n_data, sweep_at)."""
    if gp_old[0] != 0.0:
        predictions(P, c0, gp_old, gate, dirs, blend, prior_old, x, cov, extra, has, near, pred)
        absorb_errors(pred, cal_k, cal_width, hist, count, memory)
    else:
        pred[:, :] = np.nan
    before = n_dirty
    n_dirty, taken = absorb_points(P, B, c0, gp, gate, dirs, support, track, A, b, rr, wsum, near, listed, dirty,
                                   n_dirty, solved_w, growth, last, sample_mm)
    for i in range(before, n_dirty):
        k = dirty[i]
        if not in_data[k]:
            in_data[k] = True
            data_nodes[n_data] = k
            n_data += 1
    if gp[0] == 0.0:
        return n_dirty, taken, n_data, sweep_at
    count_ = min(n_dirty, budget)
    if count_:
        solve_nodes(dirty, count_, dirs, c0, gp, tp, A, b, rr, wsum, near, prior, reach, nb_off, nb_idx, nb_ang, dev, slope,
                    x, cov, excess, has, listed, solved_w)
        rest = n_dirty - count_
        for i in range(rest):
            dirty[i] = dirty[count_ + i]
        n_dirty = rest
    if n_data and sweep:
        nodes = np.empty(sweep, dtype=np.int64)
        keep = np.empty(sweep, dtype=np.bool_)
        for s in range(sweep):
            nodes[s] = data_nodes[(sweep_at + s) % n_data]
            keep[s] = listed[nodes[s]]  # a node waiting in dirty stays listed
        sweep_at = (sweep_at + sweep) % n_data
        solve_nodes(nodes, sweep, dirs, c0, gp, tp, A, b, rr, wsum, near, prior, reach, nb_off, nb_idx, nb_ang, dev, slope,
                    x, cov, excess, has, listed, solved_w)
        for s in range(sweep):
            listed[nodes[s]] = keep[s]
    return n_dirty, taken, n_data, sweep_at
