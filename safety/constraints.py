"""The safety filter's QP, built in one compiled call from a step's kinematics.

Decision variable: joint velocities qdot (n,) in rad/s. Jacobians map qdot to point
velocities in W in mm/s (so J is in mm/rad). A control barrier row keeps a value
h(q) >= h_min: dh/dt = grad_h . J qdot >= -gain (h - h_min), with `gain` in 1/s.

    cost        |J_tip qdot - v_cmd|^2 + |J_roll qdot - roll|^2 + damping |qdot|^2
    bounds      |qdot| <= qdot_max; joints approach [q_min + margin, q_max - margin]
                no faster than joint_gain x distance
    tip speed   |J_tip qdot| <= max speed, as 26 half-spaces inside the ball
    barriers    one row per monitored point (retina and lens keep-out alike)
    equalities  the RCM rows A qdot = b (with their drift correction)
"""
from __future__ import annotations

import numpy as np
from numba import njit

from safety.qp import DenseQP

# Tip speed polytope: 26 face normals (the cube's faces, edges and corners). With every
# face at distance d, the polytope holds the ball of radius d and lies within the ball
# of radius 1.13 d (maximum over directions, by linear programming); faces at
# v / _POLYTOPE_REACH keep the speed <= v and allow at least 0.87 v in any direction.
_D = np.array([v for v in np.ndindex(3, 3, 3) if v != (1, 1, 1)], dtype=float) - 1.0
_D /= np.linalg.norm(_D, axis=1, keepdims=True)
_POLYTOPE_REACH = 1.15
TIP_SPEED_ROWS = ("tip_speed",) * len(_D)


@njit(cache=True)
def barrier_rows(h_model, g_model, h_fallback, g_fallback, point_margin, margin, d_safe, always, h_lens, g_lens,
                 lens_margin, reach_mm):
    """The barrier rows of one step: (h (k + m,) mm, grad (k + m, 3), h_min (k + m,) mm,
    keep (k + m,) bool, finite). Boundary point i's clearance is the tighter of the
    model's h_model[i] (gradient g_model[i]) and the fallback's h_fallback[i] (+inf where
    the point is trusted); it must stay above d_safe + margin + point_margin[i]. The m lens
    points (h_lens: their signed distance to the lens keep-out, > 0 inside it) must stay
    outside it by lens_margin. A row further from its bound than reach_mm (what the
    speed limit can close at the barrier rate in one step's horizon) cannot become
    active and is left out, except the points marked `always` (tip and port: the
    clearance and the cutter interlock). `finite`: every value and gradient is."""
    k, m = h_model.shape[0], h_lens.shape[0]
    h = np.empty(k + m)
    grad = np.empty((k + m, 3))
    h_min = np.empty(k + m)
    keep = np.zeros(k + m, dtype=np.bool_)
    finite = True
    for i in range(k + m):
        if i < k:
            tighter = h_fallback[i] < h_model[i]
            h[i] = h_fallback[i] if tighter else h_model[i]
            for r in range(3):
                grad[i, r] = g_fallback[i, r] if tighter else g_model[i, r]
            h_min[i] = d_safe + margin + point_margin[i]
        else:
            h[i] = -h_lens[i - k]
            for r in range(3):
                grad[i, r] = -g_lens[i - k, r]
            h_min[i] = lens_margin
        keep[i] = h[i] - h_min[i] <= reach_mm or (i < k and always[i])
        if not (np.isfinite(h[i]) and np.isfinite(grad[i, 0]) and np.isfinite(grad[i, 1]) and np.isfinite(grad[i, 2])):
            finite = False
    return h, grad, h_min, keep, finite


@njit(cache=True)
def _filter_qp(J_tip, v_cmd, damping, J_roll, roll_cmd, q, q_min, q_max, qdot_max, joint_gain, joint_margin,
               max_tip_speed, D, reach, h_pts, grad_pts, J_pts, h_min_pts, gain, max_recovery):
    n = q.shape[0]
    H = np.empty((n, n))
    c = np.empty(n)
    lb = np.empty(n)
    ub = np.empty(n)
    for a in range(n):  # written out: for 3 x 6 factors a BLAS call costs more than its work
        for b in range(n):
            s = J_tip[0, a] * J_tip[0, b] + J_tip[1, a] * J_tip[1, b] + J_tip[2, a] * J_tip[2, b]
            for r in range(J_roll.shape[0]):
                s += J_roll[r, a] * J_roll[r, b]
            H[a, b] = 2.0 * (s + (damping if a == b else 0.0))
        s = J_tip[0, a] * v_cmd[0] + J_tip[1, a] * v_cmd[1] + J_tip[2, a] * v_cmd[2]
        for r in range(J_roll.shape[0]):
            s += J_roll[r, a] * roll_cmd[r]
        c[a] = -2.0 * s
        lb[a] = max(-qdot_max[a], -joint_gain * (q[a] - (q_min[a] + joint_margin)))
        ub[a] = min(qdot_max[a], joint_gain * ((q_max[a] - joint_margin) - q[a]))
    k, m = D.shape[0], h_pts.shape[0]
    G = np.empty((k + m, n))
    h = np.empty(k + m)
    for i in range(k):
        for j in range(n):
            G[i, j] = D[i, 0] * J_tip[0, j] + D[i, 1] * J_tip[1, j] + D[i, 2] * J_tip[2, j]
        h[i] = max_tip_speed / reach
    for i in range(m):  # -(grad . J) qdot <= gain (h - h_min), the recovery below h_min capped
        for j in range(n):
            G[k + i, j] = -(grad_pts[i, 0] * J_pts[i, 0, j] + grad_pts[i, 1] * J_pts[i, 1, j] + grad_pts[i, 2] * J_pts[i, 2, j])
        h[k + i] = max(gain * (h_pts[i] - h_min_pts[i]), -max_recovery)
    return H, c, lb, ub, G, h


def filter_qp(J_tip, v_cmd, damping: float, J_roll, roll_rate_cmd: float, q, q_min, q_max, qdot_max,
              joint_gain: float, joint_margin_rad: float, max_tip_speed: float, names: tuple, h_pts, grad_pts, J_pts,
              h_min_pts, gain: float, max_recovery: float, rcm_A=None, rcm_b=None) -> DenseQP:
    """The filter's DenseQP (mm, s, rad; W). Barrier rows: point i (named names[i]) with
    clearance h_pts[i] mm, gradient grad_pts[i] (3,), Jacobian J_pts[i] (3, n) mm/rad,
    kept above h_min_pts[i] mm at `gain` 1/s; below it, it must rise at gain (h_min - h),
    capped at `max_recovery` mm/s (so that a point pushed inside the margin, e.g. by a
    model update, asks for a recovery the speed limits can give instead of making the
    QP infeasible). Tip speed <= max_tip_speed mm/s; RCM rows rcm_A qdot = rcm_b."""
    n = len(q)
    f = np.asarray
    J_roll = np.zeros((0, n)) if J_roll is None else np.atleast_2d(f(J_roll, dtype=float))
    H, c, lb, ub, G, h = _filter_qp(
        f(J_tip, dtype=float), f(v_cmd, dtype=float), float(damping), J_roll,
        np.full(len(J_roll), float(roll_rate_cmd)), f(q, dtype=float), f(q_min, dtype=float), f(q_max, dtype=float),
        f(qdot_max, dtype=float), float(joint_gain), float(joint_margin_rad), float(max_tip_speed), _D, _POLYTOPE_REACH,
        f(h_pts, dtype=float).reshape(-1), f(grad_pts, dtype=float).reshape(-1, 3), f(J_pts, dtype=float).reshape(-1, 3, n),
        f(h_min_pts, dtype=float).reshape(-1), float(gain), float(max_recovery))
    A = np.zeros((0, n)) if rcm_A is None else np.atleast_2d(f(rcm_A, dtype=float))
    b = np.zeros(0) if rcm_b is None else np.atleast_1d(f(rcm_b, dtype=float))
    return DenseQP(H, c, lb, ub, G, h, A, b, TIP_SPEED_ROWS + tuple(names))
