"""The compiled pieces of a filter step that are not constraints: the fault checks, the
tracking cost, the QP's screen and warm start, the active-set memory.

The assembled step (safety.assembly) runs them around the constraints' fillers:

    faults -> tracking cost -> constraints' rows -> screen (the optimum under the
    equalities, if it satisfies every inequality) -> the previous step's active set and
    up to WARM_CHANGES single changes from it, each certified by its KKT conditions ->
    (else) DAQP, called from Python (its call from a step costs 40-110 us: 5 us warm, the
    rest its code and data fetched back after the simulation's work between calls).

Units: mm, s, rad; frame W.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from safety.qp import NEEDS_SOLVER, OPTIMAL, rows_at_bound, screen, warm_solution

# fault codes (safety.filter words them); a constraint's filler fault is CONSTRAINT_FAULT + its index
(OK, NONFINITE_Q, NONFINITE_COMMAND, NONFINITE_J_TIP, ABSURD_SPEED, STALE_MODEL, STALE_SENSOR, NONFINITE_POINTS,
 NONFINITE_ROLL, NONFINITE_TIME, NONFINITE_PENDING) = range(11)
CONSTRAINT_FAULT = 100
# the step's result codes
STEP_OPTIMAL, STEP_NEEDS_SOLVER, STEP_FAULT, STEP_QP_FAILED = 0, 1, 2, 3
ACTIVE_TOL = 1e-6  # a row within this (relative) of its bound is active (safety.qp.solve's default)
WARM_CHANGES = 4  # changes to the previous step's active set tried before DAQP (safety.qp.warm_solution)
# cfg: the filter-level numbers the step reads
CFG_DAMPING, CFG_MAX_COMMAND_SPEED, CFG_MAX_MODEL_AGE, CFG_MAX_SENSOR_AGE = range(4)


@njit(cache=True)
def all_finite(a) -> bool:
    for v in a.ravel():
        if not np.isfinite(v):
            return False
    return True


@njit(cache=True)
def input_fault(q, command, J_tip, P, J, times, pending, cfg) -> int:
    """The first fault of the step's inputs (a code above), or OK. times = [t, the model's
    time, the newest sensor sample's time] s; pending (r, n) rad the actuator's pending
    displacements (0 rows: none); cfg as CFG_*."""
    if not all_finite(q):
        return NONFINITE_Q
    if not (np.isfinite(command[0]) and np.isfinite(command[1]) and np.isfinite(command[2])):
        return NONFINITE_COMMAND
    if not np.isfinite(command[3]):  # read only with roll rows: a NaN must not pass unseen without them
        return NONFINITE_ROLL
    if not all_finite(J_tip):
        return NONFINITE_J_TIP
    if np.sqrt(command[0] ** 2 + command[1] ** 2 + command[2] ** 2) > cfg[CFG_MAX_COMMAND_SPEED]:
        return ABSURD_SPEED
    if not all_finite(times):  # an infinite stamp makes an age of -inf, which the age tests pass
        return NONFINITE_TIME
    if not (times[0] - times[1] <= cfg[CFG_MAX_MODEL_AGE]):
        return STALE_MODEL
    if not (times[0] - times[2] <= cfg[CFG_MAX_SENSOR_AGE]):
        return STALE_SENSOR
    if not (all_finite(P) and all_finite(J)):
        return NONFINITE_POINTS
    if not all_finite(pending):
        return NONFINITE_PENDING
    return OK


@njit(cache=True)
def tracking_cost(J_tip, v_cmd, J_roll, roll_cmd, damping, H, c):
    """H = 2 (J_tip^T J_tip + J_roll^T J_roll + damping I), c = -2 (J_tip^T v_cmd +
    J_roll^T roll_cmd): |J_tip qdot - v_cmd|^2 + |J_roll qdot - roll|^2 + damping |qdot|^2
    (J_roll (r, n), roll_cmd (r,)); written out: for 3 x 6 factors a BLAS call costs more
    than its work."""
    n = J_tip.shape[1]
    for a in range(n):
        for b in range(n):
            s = J_tip[0, a] * J_tip[0, b] + J_tip[1, a] * J_tip[1, b] + J_tip[2, a] * J_tip[2, b]
            for r in range(J_roll.shape[0]):
                s += J_roll[r, a] * J_roll[r, b]
            H[a, b] = 2.0 * (s + (damping if a == b else 0.0))
        s = J_tip[0, a] * v_cmd[0] + J_tip[1, a] * v_cmd[1] + J_tip[2, a] * v_cmd[2]
        for r in range(J_roll.shape[0]):
            s += J_roll[r, a] * roll_cmd[r]
        c[a] = -2.0 * s


@njit(cache=True)
def off_command(J_tip, qdot, v_cmd) -> bool:
    """The tip velocity J_tip qdot (mm/s) is off the command v_cmd by more than 1 % of its speed."""
    err2, speed2 = 0.0, 0.0
    for r in range(3):
        v = 0.0
        for j in range(qdot.shape[0]):
            v += J_tip[r, j] * qdot[j]
        err2 += (v - v_cmd[r]) ** 2
        speed2 += v_cmd[r] ** 2
    return np.sqrt(err2) > 0.01 * max(np.sqrt(speed2), 1e-9)


@njit(cache=True)
def remember_active(active, ids, G, h, lb, ub, x, tol, at_bound_out):
    """Set `active` (n_ids + 2n,) to the constraints at their bound at x: G's rows by their
    identities `ids`, then the joint bounds (lower j at n_ids + j, upper at n_ids + n + j);
    writes the indices of G's rows at their bound into at_bound_out, returns their count."""
    active[:] = False
    at_bound = rows_at_bound(G, h, x, tol)
    for i in at_bound:
        active[ids[i]] = True
    n = x.shape[0]
    base = active.shape[0] - 2 * n
    for j in range(n):
        active[base + j] = x[j] <= lb[j] + tol * (1.0 + abs(lb[j]))
        active[base + n + j] = x[j] >= ub[j] - tol * (1.0 + abs(ub[j]))
    at_bound_out[:at_bound.shape[0]] = at_bound
    return at_bound.shape[0]


@njit(cache=True)
def finish(H, c, lb, ub, G, h, A, b, ids, active, warm, at_bound_out):
    """(code, x, rows at bound): the QP's solution when the screen or (with `warm`) the
    previous step's active set or one up to WARM_CHANGES changes from it, certified, gives
    it (STEP_OPTIMAL), else STEP_NEEDS_SOLVER or STEP_QP_FAILED (non-finite data, crossed
    bounds: the Python side says which)."""
    n = c.shape[0]
    code, x = screen(H, c, lb, ub, G, h, A, b, ACTIVE_TOL)
    if code == OPTIMAL:
        active[:] = False
        return STEP_OPTIMAL, x, 0
    if code != NEEDS_SOLVER:
        active[:] = False
        return STEP_QP_FAILED, x, 0
    if warm:
        held = np.empty(ids.shape[0], dtype=np.bool_)
        for i in range(ids.shape[0]):
            held[i] = active[ids[i]]
        base = active.shape[0] - 2 * n
        certified, x_w = warm_solution(H, c, lb, ub, G, h, A, b, held, active[base:base + n].copy(),
                                       active[base + n:].copy(), ACTIVE_TOL, WARM_CHANGES)
        if certified:
            return STEP_OPTIMAL, x_w, remember_active(active, ids, G, h, lb, ub, x_w, ACTIVE_TOL, at_bound_out)
    return STEP_NEEDS_SOLVER, x, 0
