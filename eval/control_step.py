"""The closed loop's control step as one compiled call.

At 1 kHz a step is a few microseconds of arithmetic spread over some thirty small
calls: the instrument's points and Jacobians (planning.instrument_points), the model's
and the prior's distances and gradients, the coverage queries that decide which
points the model is trusted for, the barrier rows, the QP's assembly and its screen
(safety). Each of those is compiled already; between them, Python objects
(FilterInputs, PointKinematics, argument checks) cost most of the step. `control_step`
runs the same kernels in the same order from plain arrays, so the ordinary step is one
call: when the equality optimum violates an inequality, the previous step's active
set is tried first (safety.qp.warm_solution, certified by the KKT conditions), and DAQP
only decides when that guess is not this step's.

The reference stays safety.SafetyFilter on eval.closed_loop.FilterSystem.inputs: what
the run logs hold and `vitreoguard replay` re-runs. Whatever is not the ordinary path
(any fault, a point on the plane of the model ellipsoid's smallest axis, a QP the
screen finds non-finite or with crossed bounds, a solver failure) comes back as
REFERENCE, and the caller runs the reference filter, which also says why. Tests hold
the two equal.

Units: mm, s, rad; frame W.
"""
from __future__ import annotations

import time
from typing import NamedTuple

import numpy as np
from numba import njit

from models._eberly import generic_distance_and_gradient
from models.coverage import _nearest_and_worst, band_chord
from models.sphere import sphere_distance_and_gradient
from planning.instrument_points import _LENS_NAMES, _NAMES, instrument_kinematics, kinematics_arguments
from safety.constraints import _D, _POLYTOPE_REACH, TIP_SPEED_ROWS, _filter_qp, barrier_rows
from safety.filter import _off_command
from safety.qp import (
    _NEEDS_SOLVER, _OPTIMAL, DenseQP, QPResult, _finite, _rows_at_bound, _screen, solve_by_solver, warm_solution,
)

OPTIMAL, NEEDS_SOLVER, REFERENCE = 0, 1, 2  # control_step's codes


class StepResult(NamedTuple):
    """control_step's result (mm, rad, s; W): `code`; `x` (6,) rad/s when OPTIMAL; k
    boundary points (k_used of them against the model), m lens points, P_W (k + m + 1,
    3) mm (tip, port, shaft, lens points, the shaft's point at the trocar); J_tip (3, 6)
    mm/rad; the RCM error, the smallest clearance and the port's (mm); the QP's kept
    barrier rows and rows at their bound (counts; the rows in the workspace); whether
    J_tip x is off the command by > 1 %."""

    code: int
    x: np.ndarray
    k: int
    k_used: int
    m: int
    P_W: np.ndarray
    J_tip: np.ndarray
    rcm_error_mm: float
    clearance_mm: float
    port_clearance_mm: float
    n_rows: int
    n_at_bound: int
    off_command: bool
PRIOR, SPHERE, ELLIPSOID = 0, 1, 2  # the model the filter uses
ACTIVE_TOL = 1e-6  # safety.qp.solve's default: a row within this (relative) of its bound is active
_ROW_NAMES = tuple(f"boundary:{n}" for n in _NAMES), tuple(f"lens:{n}" for n in _LENS_NAMES)


@njit(cache=True)
def _shape_distance(kind, center, rotation, radii, P):
    """(h (M,) mm, grad (M, 3), generic): the signed distance and gradient of the sphere
    (kind SPHERE or PRIOR: radius radii[0]) or ellipsoid at P (M, 3); generic False when a
    point lies on the ellipsoid's smallest axis's plane (left to the reference)."""
    if kind == ELLIPSOID:
        h, g, generic = generic_distance_and_gradient(center, rotation, radii, P)
        ok = True
        for i in range(generic.shape[0]):
            ok = ok and generic[i]
        return h, g, ok
    h, g = sphere_distance_and_gradient(center, radii[0], P)
    return h, g, True


@njit(cache=True)
def _unit_directions(P, center):
    """(M, 3) unit directions of P (M, 3) mm from center (models.coverage.CoverageView)."""
    V = np.empty(P.shape)
    for i in range(P.shape[0]):
        v0, v1, v2 = P[i, 0] - center[0], P[i, 1] - center[1], P[i, 2] - center[2]
        n = max(np.sqrt(v0 * v0 + v1 * v1 + v2 * v2), 1e-12)
        V[i, 0], V[i, 1], V[i, 2] = v0 / n, v1 / n, v2 / n
    return V


N_TIP_ROWS = _D.shape[0]
N_IDS = N_TIP_ROWS + len(_NAMES) + len(_LENS_NAMES) + 12  # tip speed rows, points, lens points, joint bounds
_MAX_G = N_TIP_ROWS + len(_NAMES) + len(_LENS_NAMES)  # rows of G at most
WORKSPACE_SIZES = (36 + 6 + 6 + 6 + 12 + 2 + 7 * _MAX_G, 2 * _MAX_G)  # floats, ints


@njit(cache=True)
def workspace_views(wsf, wsi):
    """(H (6, 6), c, lb, ub (6,), A (2, 6), b (2,), G (_MAX_G, 6), h (_MAX_G,), rows (_MAX_G,),
    at_bound (_MAX_G,)): the step's QP and row lists as views of the float and int buffers
    wsf, wsi (WORKSPACE_SIZES), where control_step leaves them (returning them would cost
    a Python object each, per step)."""
    g = 68 + 6 * _MAX_G
    return (wsf[0:36].reshape((6, 6)), wsf[36:42], wsf[42:48], wsf[48:54], wsf[54:66].reshape((2, 6)), wsf[66:68],
            wsf[68:g].reshape((_MAX_G, 6)), wsf[g:g + _MAX_G], wsi[:_MAX_G], wsi[_MAX_G:])


@njit(cache=True)
def row_ids(rows, k_used):
    """The identity (0..N_IDS) of each row of the filter QP's G: the tip speed polytope's
    faces, then the kept barrier rows `rows` by their point (boundary points below k_used,
    then lens points): an identity survives the rows left out or kept between steps."""
    ids = np.empty(N_TIP_ROWS + rows.shape[0], dtype=np.int64)
    for i in range(N_TIP_ROWS):
        ids[i] = i
    for r in range(rows.shape[0]):
        j = rows[r]
        ids[N_TIP_ROWS + r] = N_TIP_ROWS + j if j < k_used else N_TIP_ROWS + len(_NAMES) + j - k_used
    return ids


@njit(cache=True)
def remember_active(active_ids, ids, G, h, lb, ub, x, tol):
    """Set active_ids to the constraints at their bound at x (G's rows by `ids`, then the
    joint bounds: lower j at N_IDS - 12 + j, upper at N_IDS - 6 + j); the rows of G at
    their bound (relative tol, as safety.qp reports them)."""
    active_ids[:] = False
    at_bound = _rows_at_bound(G, h, x, tol)
    for i in at_bound:
        active_ids[ids[i]] = True
    n = x.shape[0]
    for j in range(n):
        active_ids[N_IDS - 2 * n + j] = x[j] <= lb[j] + tol * (1.0 + abs(lb[j]))
        active_ids[N_IDS - n + j] = x[j] >= ub[j] - tol * (1.0 + abs(ub[j]))
    return at_bound


@njit(cache=True)
def warm_guess(active_ids, ids, n):
    """(held rows of G (by their `ids`), held lower bounds (n,), held upper bounds (n,)):
    the previous step's active set (active_ids) on this step's QP."""
    held_rows = np.empty(ids.shape[0], dtype=np.bool_)
    for i in range(ids.shape[0]):
        held_rows[i] = active_ids[ids[i]]
    return held_rows, active_ids[N_IDS - 2 * n:N_IDS - n].copy(), active_ids[N_IDS - n:].copy()


# control_step's constant arguments in one float array (one argument instead of twenty:
# numba's dispatch costs ~0.08 us an argument, every step): sizes in this order, then the
# lens offsets (mm) to the end
_STATICS = ("S", 36, "R_home_I", 9, "p_home_I", 3, "p_WC", 3, "tip_x", 1, "port_I", 3, "spacing", 1, "n_shaft", 1,
            "min_depth", 1, "rcm_gain", 1, "prior_center", 3, "prior_radii", 3, "lens_center", 3, "lens_rotation", 9,
            "lens_radii", 3, "q_min", 6, "q_max", 6, "qdot_max", 6, "cfg", 15)
_SO = np.concatenate([[0], np.cumsum(_STATICS[1::2])])  # offsets
# the model's: kind, center (3), rotation (9), radii (3), margin, has_coverage, coverage centre (3)
_MO = np.concatenate([[0], np.cumsum((1, 3, 9, 3, 1, 1, 3))])


def pack_statics(**parts) -> np.ndarray:
    """The float array of control_step's constants, named as in _STATICS (+ lens_offsets)."""
    flat = [np.asarray(parts[name], dtype=float).reshape(-1) for name in _STATICS[::2]]
    if [len(f) for f in flat] != list(_STATICS[1::2]):
        raise ValueError(f"pack_statics: sizes {[len(f) for f in flat]}, expected {list(_STATICS[1::2])}")
    return np.concatenate(flat + [np.asarray(parts["lens_offsets"], dtype=float).reshape(-1)])


@njit(cache=True)
def unpack_statics(st):
    """pack_statics' parts, as views (in _STATICS' order, then the lens offsets)."""
    o = _SO
    return (st[o[0]:o[1]].reshape((6, 6)), st[o[1]:o[2]].reshape((3, 3)), st[o[2]:o[3]], st[o[3]:o[4]], st[o[4]],
            st[o[5]:o[6]], st[o[6]], int(st[o[7]]), st[o[8]], st[o[9]], st[o[10]:o[11]], st[o[11]:o[12]],
            st[o[12]:o[13]], st[o[13]:o[14]].reshape((3, 3)), st[o[14]:o[15]], st[o[15]:o[16]], st[o[16]:o[17]],
            st[o[17]:o[18]], st[o[18]:o[19]], st[o[19]:])


def pack_model(kind: int, center, rotation, radii, margin: float, has_coverage: bool, coverage_center) -> np.ndarray:
    """The float array of control_step's model arguments (unpack_model)."""
    return np.concatenate([[kind], np.asarray(center, dtype=float).reshape(3), np.asarray(rotation, dtype=float).reshape(9),
                           np.asarray(radii, dtype=float).reshape(3), [margin, float(has_coverage)],
                           np.asarray(coverage_center, dtype=float).reshape(3)])


@njit(cache=True)
def unpack_model(md):
    """(kind, center, rotation (3, 3), radii, margin, has_coverage, coverage centre) of pack_model's array."""
    o = _MO
    return (int(md[0]), md[o[1]:o[2]], md[o[2]:o[3]].reshape((3, 3)), md[o[3]:o[4]], md[o[4]], md[o[5]] != 0.0,
            md[o[6]:o[7]])


@njit(cache=True)
def control_step(q, command, t_s, sensor_t_s, model_t_s, statics, model, cov_dirs, cov_misfit, active_ids, wsf, wsi):
    """One filter step (FilterSystem.inputs + SafetyFilter), compiled.

    q (6,) rad; command (4,): tip velocity (3,) mm/s in W and roll rate rad/s; t_s,
    sensor_t_s and model_t_s (s): now, the last sensor sample, the model's time. Kinematics: planning.instrument_points'
    kinematics_arguments. The model: `kind` (PRIOR, SPHERE, ELLIPSOID) with (center (3,)
    mm, rotation (3, 3), radii (3,) mm; a sphere's radius in radii[0]) and its
    uncertainty margin (mm); the prior sphere (prior_center, prior_radii[0]);
    the coverage: its centre, covered directions (N, 3) and their misfit (N,) mm (zeros
    without a model misfit). The lens keep-out ellipsoid; joint limits (rad, rad/s).
    cfg: the filter's and the loop's parameters (CompiledStep builds it). active_ids
    (N_IDS,) bool: the constraints active at the previous step's solution (row_ids),
    the guess tried when the equality optimum is not feasible; updated in place.

    Returns a StepResult and leaves in the
    workspace (workspace_views of wsf, wsi) the QP (its G and h: the n_rows + N_TIP_ROWS
    first rows), its kept rows (indices into the k_used boundary points, then the lens
    points) and the rows of G at their bound (none when the equality optimum holds, as
    safety.qp.solve reports)."""
    (S, R_home_I, p_home_I, p_WC, tip_x, port_I, spacing, n_shaft, min_depth, rcm_gain, prior_center, prior_radii,
     lens_center, lens_rotation, lens_radii, q_min, q_max, qdot_max, cfg, lens_offsets) = unpack_statics(statics)
    kind, center, rotation, radii, margin, has_coverage, cov_center = unpack_model(model)
    d_safe, gain, lens_margin, joint_gain, joint_margin = cfg[0], cfg[1], cfg[2], cfg[3], cfg[4]
    max_tip_speed, max_command_speed, damping, max_model_age, max_sensor_age = cfg[5], cfg[6], cfg[7], cfg[8], cfg[9]
    max_recovery, trust_rad, cos_misfit, chord_trust, chord_misfit = cfg[10], cfg[11], cfg[12], cfg[13], cfg[14]
    P, J, k, m, J_roll, rcm_A, rcm_b, rcm_error, _, _ = instrument_kinematics(
        S, R_home_I, p_home_I, q, p_WC, tip_x, port_I, spacing, n_shaft, min_depth, lens_offsets, rcm_gain)
    J_tip = J[0].copy()
    k_used = 2 if kind == PRIOR else k
    x = np.zeros(6)
    speed = np.sqrt(command[0] ** 2 + command[1] ** 2 + command[2] ** 2)
    fault = not (_finite(q) and _finite(command[:3]) and _finite(P) and _finite(J)
                 and speed <= max_command_speed and t_s - model_t_s <= max_model_age
                 and t_s - sensor_t_s <= max_sensor_age and np.isfinite(margin) and margin >= 0.0)
    if fault:
        active_ids[:] = False
        return StepResult(REFERENCE, x, k, k_used, m, P, J_tip, rcm_error, np.nan, np.nan, 0, 0, True)
    # which points the model is trusted for, and its measured misfit near them (CoverageView)
    trusted = np.ones(k_used, dtype=np.bool_)
    misfit = np.zeros(k_used)
    if kind != PRIOR and has_coverage:  # without covered directions: no point is trusted (angle pi)
        V = _unit_directions(P[:k_used], cov_center)
        # one scan for both queries, in the z band of the wider angle (a direction beyond an
        # angle's chord in z is beyond the angle: the band decides alike)
        best, misfit = _nearest_and_worst(V, cov_dirs, cov_misfit, cos_misfit, max(chord_trust, chord_misfit))
        for i in range(2):
            trusted[i] = np.arccos(min(max(best[i], -1.0), 1.0)) <= trust_rad
    h_model, g_model, generic = _shape_distance(kind, center, rotation, radii, P[:k_used])
    h_fallback = np.full(k_used, np.inf)
    g_fallback = np.zeros((k_used, 3))
    if kind != PRIOR and not trusted.all():  # the prior as fallback where the model is not trusted
        h_p, g_p, _ = _shape_distance(SPHERE, prior_center, rotation, prior_radii, P[:k_used])
        for i in range(k_used):
            if not trusted[i]:
                h_fallback[i] = h_p[i]
                g_fallback[i] = g_p[i]
    h_lens, g_lens, lens_generic = _shape_distance(ELLIPSOID, lens_center, lens_rotation, lens_radii, P[k:k + m])
    if not (generic and lens_generic):
        active_ids[:] = False
        return StepResult(REFERENCE, x, k, k_used, m, P, J_tip, rcm_error, np.nan, np.nan, 0, 0, True)
    always = np.zeros(k_used, dtype=np.bool_)
    always[:2] = True
    h, grad, h_min, keep, finite = barrier_rows(h_model, g_model, h_fallback, g_fallback, misfit, margin, d_safe, always,
                                                h_lens, g_lens, lens_margin, max_tip_speed / gain)
    if not finite:
        active_ids[:] = False
        return StepResult(REFERENCE, x, k, k_used, m, P, J_tip, rcm_error, np.nan, np.nan, 0, 0, True)
    clearance = h[:k_used].min()
    rows = np.flatnonzero(keep)
    J_pts = np.empty((rows.shape[0], 3, 6))
    for r in range(rows.shape[0]):
        J_pts[r] = J[rows[r]] if rows[r] < k_used else J[k + rows[r] - k_used]
    H, c, lb, ub, G, hv = _filter_qp(J_tip, command[:3].copy(), damping, J_roll.reshape(1, 6), np.full(1, command[3]), q,
                                     q_min, q_max, qdot_max, joint_gain, joint_margin, max_tip_speed, _D, _POLYTOPE_REACH,
                                     h[rows], grad[rows], J_pts, h_min[rows], gain, max_recovery)
    code, x = _screen(H, c, lb, ub, G, hv, rcm_A, rcm_b, ACTIVE_TOL)
    at_bound = np.zeros(0, dtype=np.int64)
    if code == _OPTIMAL:
        active_ids[:] = False
    elif code == _NEEDS_SOLVER:
        ids = row_ids(rows, k_used)
        certified, x_w = warm_solution(H, c, lb, ub, G, hv, rcm_A, rcm_b, *warm_guess(active_ids, ids, 6), ACTIVE_TOL)
        if certified:
            code, x = _OPTIMAL, x_w
            at_bound = remember_active(active_ids, ids, G, hv, lb, ub, x, ACTIVE_TOL)
    else:
        active_ids[:] = False
    H_w, c_w, lb_w, ub_w, A_w, b_w, G_w, h_w, rows_w, bound_w = workspace_views(wsf, wsi)
    H_w[:], c_w[:], lb_w[:], ub_w[:], A_w[:], b_w[:] = H, c, lb, ub, rcm_A, rcm_b
    G_w[:G.shape[0]], h_w[:G.shape[0]], rows_w[:rows.shape[0]], bound_w[:at_bound.shape[0]] = G, hv, rows, at_bound
    out = OPTIMAL if code == _OPTIMAL else (NEEDS_SOLVER if code == _NEEDS_SOLVER else REFERENCE)
    return StepResult(out, x, k, k_used, m, P, J_tip, rcm_error, clearance, h[1], rows.shape[0], at_bound.shape[0],
                      _off_command(J_tip, x, command))


def _writeable(a) -> np.ndarray:
    """`a` as a C-contiguous, writeable float array, copied only when it is not one (the
    model's frozen arrays are read-only, which numba would compile for separately)."""
    if isinstance(a, np.ndarray) and a.dtype == np.float64 and a.flags.c_contiguous and a.flags.writeable:
        return a
    return np.array(a, dtype=float, order="C")


def row_names(rows: np.ndarray, k_used: int) -> tuple:
    """The QP's inequality row names: the tip speed polytope's, then the kept barrier rows
    (indices below k_used: boundary points; the rest: lens points), as SafetyFilter names them."""
    boundary, lens = _ROW_NAMES
    return TIP_SPEED_ROWS + tuple(boundary[i] if i < k_used else lens[i - k_used] for i in rows.tolist())


class CompiledStep:
    """`step(t_s, q, command, snap, sensor_t_s)` -> (FilterOutput or None, StepResult):
    control_step with this loop's robot, configuration and prior; None where the
    reference filter must decide (REFERENCE, or a solver failure). `snap` is an
    eval.closed_loop.ModelSnapshot: its arrays are unpacked once per snapshot. It keeps
    the last step's active set as the next step's guess: `reset` between runs."""

    def __init__(self, robot, config, prior, safety_filter):
        self.filter, self.solver = safety_filter, config.filter.solver
        f = config.filter
        (S, R_home_I, p_home_I), (p_WC, tip_x, port_I, spacing, n_shaft, min_depth, lens_offsets, rcm_gain) = \
            kinematics_arguments(robot, robot.p_WC, config.points)
        lens = robot.scenario.lens_W
        self._prior_center, self._prior_radii = _writeable(prior.center), np.full(3, float(prior.radius))
        self._statics = pack_statics(
            S=S, R_home_I=R_home_I, p_home_I=p_home_I, p_WC=p_WC, tip_x=tip_x, port_I=port_I, spacing=spacing,
            n_shaft=n_shaft, min_depth=min_depth, rcm_gain=rcm_gain, prior_center=self._prior_center,
            prior_radii=self._prior_radii, lens_center=lens.center, lens_rotation=lens.rotation, lens_radii=lens.radii,
            q_min=robot.q_lower, q_max=robot.q_upper, qdot_max=robot.qdot_max, lens_offsets=lens_offsets,
            cfg=[f.d_safe_mm, f.gain_per_s, f.lens_margin_mm, f.joint_gain_per_s, f.joint_margin_rad, f.max_tip_speed_mm_s,
                 f.max_command_speed_mm_s, f.damping, f.max_model_age_s, f.max_sensor_age_s, f.max_recovery_mm_s,
                 np.radians(config.trust_angle_deg), np.cos(np.radians(config.misfit_angle_deg)),
                 band_chord(np.radians(config.trust_angle_deg)), band_chord(np.radians(config.misfit_angle_deg))])
        self._margins = config.margins
        self._key, self._args, self._prior = (0, 0, "", 0.0), (), True  # matches no snapshot
        self._names = {}  # (k_used, kept rows, rows at bound) -> the active constraints' names
        self._active = np.zeros(N_IDS, dtype=np.bool_)  # control_step's active_ids
        self._wsf, self._wsi = np.zeros(WORKSPACE_SIZES[0]), np.zeros(WORKSPACE_SIZES[1], dtype=np.int64)
        self._ws = workspace_views(self._wsf, self._wsi)

    def _arguments(self, snap) -> tuple:
        """control_step's arguments after the times: the constants, the snapshot's model
        (kind, center, rotation, radii, margin, the coverage) and the step's state; made
        once per model: a snapshot that differs from the last one only in its time (the
        model system stamps every packet) reuses them."""
        shape, cov, res = snap.shape, snap.coverage, snap.residual_mm
        last_shape, last_cov, last_kind, last_res = self._key
        if not (shape is last_shape and cov is last_cov and snap.kind == last_kind
                and (res == last_res or (res != res and last_res != last_res))):  # NaN: no residual
            if shape is None:
                kind, center, rotation, radii = PRIOR, self._prior_center, np.eye(3), self._prior_radii
            elif hasattr(shape, "radii"):
                kind, center, rotation, radii = ELLIPSOID, shape.center, shape.rotation, shape.radii
            else:
                kind, center, rotation, radii = SPHERE, shape.center, np.eye(3), np.full(3, float(shape.radius))
            has_coverage = cov is not None and shape is not None
            if not has_coverage:
                dirs, misfit, cov_center = np.zeros((0, 3)), np.zeros(0), np.zeros(3)
            else:
                dirs, cov_center = cov._dirs, cov.center_W
                misfit = np.zeros(len(dirs)) if cov._misfit is None else cov._misfit
            model = pack_model(kind, center, rotation, radii, float(snap.margin_mm(self._margins)), has_coverage, cov_center)
            w = _writeable  # one array type for every snapshot: one compiled specialisation
            self._args = (self._statics, model, w(dirs), w(misfit), self._active, self._wsf, self._wsi)
            self._key, self._prior = (shape, cov, snap.kind, res), kind == PRIOR
        return self._args

    def _active_names(self, k_used: int, rows: np.ndarray, at_bound: np.ndarray) -> tuple:
        """The sorted names of the QP's rows at their bound (`at_bound`: indices into its
        rows, the tip speed polytope's then the kept barrier `rows`), kept per (k_used,
        rows, at_bound): a boundary held over many steps is named once."""
        key = (k_used, rows.tobytes(), at_bound.tobytes())
        active = self._names.get(key)
        if active is None:
            names = row_names(rows, k_used)
            active = tuple(sorted({names[i] for i in at_bound.tolist()}))
            if len(self._names) >= 4096:  # bounded: the combinations a run meets are few
                self._names.clear()
            self._names[key] = active
        return active

    def reset(self) -> None:
        """Forget the previous step's active set (a new run)."""
        self._active[:] = False

    def step(self, t_s: float, q: np.ndarray, command: np.ndarray, snap, sensor_t_s: float):
        t0 = time.perf_counter()
        args = self._arguments(snap)
        r = control_step(q, command, t_s, sensor_t_s, t_s if self._prior else snap.t_s, *args)
        code, x, k_used, n_rows, n_bound = r.code, r.x, r.k_used, r.n_rows, r.n_at_bound
        if code == REFERENCE:
            return None, r
        H, c, lb, ub, A, b, G, h, rows, at_bound = self._ws
        if code == OPTIMAL:
            active = self._active_names(k_used, rows[:n_rows], at_bound[:n_bound]) if n_bound else ()
            result = QPResult(x, "ok", active, 1e6 * (time.perf_counter() - t0))
            return self.filter.output(result, float(r.clearance_mm), float(r.port_clearance_mm), r.off_command), r
        m = N_TIP_ROWS + n_rows
        qp = DenseQP(H, c, lb, ub, G[:m], h[:m], A, b, row_names(rows[:n_rows], k_used))  # views: used in this call only
        result = solve_by_solver(qp, self.solver, ACTIVE_TOL, t0)
        if not result.ok:
            self.reset()
            return None, r
        remember_active(self._active, row_ids(rows[:n_rows], k_used), qp.G, qp.h, qp.lb, qp.ub, result.x, ACTIVE_TOL)
        off = _off_command(r.J_tip, result.x, command)
        return self.filter.output(result, float(r.clearance_mm), float(r.port_clearance_mm), off), r
