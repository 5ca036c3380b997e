"""A stack of constraints compiled into one filter step, with its workspace, the names
of its rows and the words for its faults.

`ConstraintStack(constraints, groups, kernels, config, kinematics)` assembles the step
(safety.assembly) once; `solve(...)` runs it on given points, `solve_at(...)` on the
points of the kinematics kernel at q. A step the compiled code cannot finish (the
optimum under the equalities violates an inequality and the remembered active set is
not this step's) goes to the solver (safety.qp, DAQP by default); a fault or a failed
QP gives zero velocity and the reason.

Recovery held. A barrier row with a negative right-hand side asks a point that is already
inside its margin (a model update raised the margin, an actuator still carrying the robot
in) to move back out at up to the recovery rate. When no velocity meets every row, and
some rows are such recovery rows, the step is solved again with each recovery row asking
only that its point come no closer (right-hand side 0): the robot keeps every other rule
and holds its recovering points, with RECOVERY_HELD as its reason and among its active
rows (ok, an intervention), instead of a zero command that the actuator would still carry
on from.

Correction eased. An equality constraint whose right-hand side corrects a drift
(`drift_correction`: the RCM's b = gain x the predicted lateral error, its rows' left side
the pivot itself) can ask for a correction that no velocity meeting the other rows gives:
an acceleration-limited robot's predicted trocar error jumps when its velocity changes,
and the correction with it (measured: 7 to 15 mm/s in one step, the tip, port and two
shaft points recovering at 5 mm/s, detached eye, local model). When neither the step nor
its held form solves, the step is solved again with those right-hand sides scaled by
each of EASED_SCALES in turn (the recovery rows as asked, then held): the shaft still
pivots about the trocar, and its error decays more slowly that step, or, at 0, stays
where the actuator's motion leaves it (bounded by the constraint's own planned stop).
CORRECTION_EASED (and RECOVERY_HELD when held) lead its active rows and its reason.
Only a QP infeasible even so stops the robot ("QP: infeasible ..."). Steps whose QP is
feasible are not touched. Units: mm, s, rad; frame W.
"""
from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from safety import step_core as core
from safety.assembly import assemble, row_id_bases, workspace_layout
from safety.inputs import FilterConfig, FilterOutput
from safety.qp import DenseQP, QPResult, solve, solve_by_solver

RECOVERY_HELD = "recovery held"  # an active-row name: the step held its recovering points (module docstring)
CORRECTION_EASED = "correction eased"  # an active-row name: the step scaled its drift corrections down (module docstring)
EASED_SCALES = (0.5, 0.0)  # the drift corrections' scales tried, in order, on a step no other form solves
RELAXATIONS = (CORRECTION_EASED, RECOVERY_HELD)  # in the order they lead a relaxed step's active rows and reason
_FAULT_WORDS = {core.NONFINITE_Q: "non-finite q", core.NONFINITE_COMMAND: "non-finite v_cmd_W",
                core.NONFINITE_J_TIP: "non-finite J_tip", core.NONFINITE_ROLL: "non-finite roll_rate_cmd",
                core.NONFINITE_TIME: "non-finite time stamp (t_s, model_time_s or sensor_time_s)",
                core.NONFINITE_PENDING: "non-finite pending actuator motion"}


def relaxations(reason: str) -> tuple[str, ...]:
    """The relaxations (RELAXATIONS) a step with this FilterOutput reason was solved under."""
    return tuple(w for w in reason.split(", ") if w in RELAXATIONS)


class ConstraintStack:
    """The constraints (in row order) over point `groups` (name -> capacity, in the order
    of the kinematics' ranges), field slots `kernels` (slot -> compiled kernel), the
    filter-level `config`, an optional `kinematics` kernel or (kernel, pose kernel) pair
    (safety.assembly), and
    `point_names(group, count)` for the rows' names. `port`: (group, index) of the cutter
    port, whose clearance opens the cutter interlock (None: no interlock)."""

    def __init__(self, constraints, groups: dict, kernels: dict, config: FilterConfig, kinematics=None,
                 point_names=None, port: tuple | None = None, n_joints: int = 6):
        self.constraints, self.groups, self.config = tuple(constraints), dict(groups), config
        self.index = {g: i for i, g in enumerate(self.groups)}
        self.slots = sorted({c.field for c in self.constraints if c.field is not None})
        self._size(n_joints)
        self._port = port
        self.module = assemble(self.constraints, self.index, kernels, kinematics, self.groups, self.layout,
                               None if port is None else (self.index[port[0]], int(port[1])))
        self._names = point_names or (lambda group, count: tuple(f"{group}{i}" for i in range(count)))
        self.cfg = np.array([config.damping, config.max_command_speed_mm_s, config.max_model_age_s,
                             config.max_sensor_age_s])
        self._names_cache: dict = {}
        self._intervening = {c.name for c in self.constraints if c.intervenes}

    def _size(self, n: int) -> None:
        """The workspace for n joints: ids per inequality constraint, buffers for the QP."""
        self.n = n
        self._no_pending = np.zeros((0, n))
        bases, n_ids = row_id_bases(self.constraints, self.groups)
        self._id_owner = [None] * n_ids  # identity -> (constraint index, row within it)
        m_cap = p_cap = 0
        eased = []  # per equality row: its right-hand side is a drift correction (module docstring)
        for i, c in enumerate(self.constraints):
            rows = c.max_rows(self.groups.get(c.group, 0))
            if c.kind == "inequality":
                self._id_owner[bases[i]:bases[i] + rows] = [(i, r) for r in range(rows)]
                m_cap += rows
            elif c.kind == "equality":
                p_cap += rows
                eased += [bool(c.drift_correction)] * rows
        self._eased = np.array(eased, dtype=bool)
        self.active = np.zeros(len(self._id_owner) + 2 * n, dtype=np.bool_)
        self.layout = (n, m_cap, p_cap, sum(self.groups.values()))
        parts, size = workspace_layout(*self.layout)
        self.wsf, self.wsi = np.zeros(size), np.zeros(2 * m_cap, dtype=np.int64)
        v = {name: self.wsf[a:b].reshape(shape) for name, (a, b, shape) in parts.items()}
        # the step's workspace as views (H, c, lb, ub, G, h, ids, A, b, point_h, rows at bound)
        self.ws = (v["H"], v["c"], v["lb"], v["ub"], v["G"], v["h"], self.wsi[:m_cap], v["A"], v["b"], v["point_h"],
                   self.wsi[m_cap:])
        self.point_bound = v["point_bound"]  # the last step's bound per point on the true clearance (point_barrier)
        self.set_params()

    def reset(self) -> None:
        """Forget the previous step's active set (a new run)."""
        self.active[:] = False

    def set_params(self, constraints=None) -> None:
        """Re-read every constraint's params(); with `constraints`, first take those in place
        of the stack's (the same types, groups and fields in the same order: new numbers,
        the same compiled step), else ValueError."""
        if constraints is not None:
            constraints = tuple(constraints)
            if [c.key() for c in constraints] != [c.key() for c in self.constraints]:
                raise ValueError("ConstraintStack.set_params: the constraints must match the stack's, in order")
            self.constraints = constraints
        params = [c.params() for c in self.constraints]
        self.spo = np.cumsum([0] + [len(p) for p in params]).astype(np.int64)
        self.spall = np.ascontiguousarray(np.concatenate(params) if params else np.zeros(0), dtype=float)

    def solve(self, q, command, times, J_tip, J_roll, P, J, ranges, fields: tuple, R_WI=None, p_WI=None,
              warm: bool = False, pending=None, X_WI_end=None):
        """(FilterOutput, raw step result) on given points: q (n,) rad, command (4,) [tip
        velocity mm/s, roll rad/s], times [t, model time, sensor time] s, J_tip (3, n),
        J_roll (r, n), P (K, 3) mm, J (K, 3, n), ranges (groups, 2), `fields` the
        params of each field slot in self.slots' order, `pending` (r, n) rad the
        actuator's pending displacements (None: none modelled), `X_WI_end` (R (3, 3),
        p (3,) mm) the instrument's pose once they are carried out (None: the present one)."""
        t0 = time.perf_counter()
        R = np.eye(3) if R_WI is None else R_WI
        p = np.zeros(3) if p_WI is None else p_WI
        R_end, p_end = (R, p) if X_WI_end is None else X_WI_end
        pending = self._no_pending if pending is None else pending
        r = self.module.step(q, command, times, self.cfg, J_tip, J_roll, P, J, ranges, R, p, R_end, p_end, pending,
                             self.spall, self.spo, *fields, self.active, warm, self.wsf, self.wsi)
        return self.output(r, q, command, times, J_tip, P, ranges, t0, warm), r

    def solve_at(self, q, command, times, kp, fields: tuple, pending=None):
        """(FilterOutput, raw step result, P, ranges, J_tip, rcm error mm) with the points
        of the kinematics kernel (params kp) at q, warm started from the previous step
        (`pending` as in solve)."""
        t0 = time.perf_counter()
        pending = self._no_pending if pending is None else pending
        r, P, ranges, J_tip, rcm_error = self.module.step_at(q, command, times, self.cfg, kp, pending, self.spall, self.spo,
                                                              *fields, self.active, True, self.wsf, self.wsi)
        return self.output(r, q, command, times, J_tip, P, ranges, t0, True), r, P, ranges, J_tip, rcm_error

    def qp(self, r, ranges) -> DenseQP | None:
        """The QP a step with raw result `r` left in the workspace (None after a fault)."""
        code, _, _, _, m, p, _, _, _, _ = r
        if code == core.STEP_FAULT:
            return None
        H, c, lb, ub, G, h, ids, A, b, _, _ = self.ws
        return DenseQP(H.copy(), c.copy(), lb.copy(), ub.copy(), G[:m].copy(), h[:m].copy(), A[:p].copy(), b[:p].copy(),
                       self.row_names(ids[:m], ranges))

    def output(self, r, q, command, times, J_tip, P, ranges, t0: float, warm: bool) -> FilterOutput:
        code, fault, detail, x, m, p, n_bound, clearance, port, off = r
        if code == core.STEP_FAULT:
            return FilterOutput(np.zeros(len(q)), False, self.fault_reason(fault, detail, q, command, times, P, ranges))
        ids, at_bound = self.ws[6], self.ws[10]
        port = None if port != port else port  # NaN: no port point this step (or no interlock)
        if code == core.STEP_OPTIMAL:
            active = self.active_names(ids[:m], at_bound[:n_bound], ranges) if n_bound else ()
            return self.finished(QPResult(x, "ok", active, 1e6 * (time.perf_counter() - t0)), clearance, port, off)
        H, c, lb, ub, G, h, _, A, b, _, _ = self.ws
        qp = DenseQP(H, c, lb, ub, G[:m], h[:m], A[:p], b[:p], RowNames(self, ids[:m].copy(), ranges))
        result = solve(qp, self.config.solver) if code == core.STEP_QP_FAILED else \
            solve_by_solver(qp, self.config.solver, core.ACTIVE_TOL, t0)
        if not result.ok and result.reason.startswith("infeasible"):
            relaxed = self.relaxed(qp, t0)
            if relaxed is not None:
                result, warm = relaxed, False  # the relaxed rows are not the step's: nothing to remember
        if not result.ok:
            self.reset()
            return FilterOutput(np.zeros(len(q)), False, f"QP: {result.reason}", min_clearance_mm=float(clearance))
        if warm:
            core.remember_active(self.active, ids[:m], qp.G, qp.h, lb, ub, result.x, core.ACTIVE_TOL, at_bound)
        return self.finished(result, clearance, port, bool(core.off_command(J_tip, result.x, command)))

    def relaxed(self, qp: DenseQP, t0: float) -> QPResult | None:
        """The infeasible step's QP solved in its relaxed forms, in order (module docstring):
        recovery held; then each of EASED_SCALES on the drift corrections, with the recovery
        rows as asked, then held. The first that solves, its relaxations leading its active
        rows; None when none does. The eased rows are the equality rows in the constraints'
        order (each equality writes its max_rows)."""
        recovering = bool(np.any(qp.h < 0.0))
        eased = self._eased if len(qp.b) == len(self._eased) and bool(np.any(qp.b[self._eased] != 0.0)) else None
        forms = [(1.0, True)] if recovering else []
        if eased is not None:
            for scale in EASED_SCALES:
                forms += [(scale, False)] + ([(scale, True)] if recovering else [])
        for scale, hold in forms:
            b = qp.b if scale == 1.0 else np.where(eased, scale * qp.b, qp.b)
            result = solve(qp._replace(h=np.maximum(qp.h, 0.0) if hold else qp.h, b=b), self.config.solver)
            if result.ok:
                marks = ((CORRECTION_EASED,) if scale < 1.0 else ()) + ((RECOVERY_HELD,) if hold else ())
                return result._replace(active=(*marks, *result.active), solve_us=1e6 * (time.perf_counter() - t0))
        return None

    def finished(self, result: QPResult, clearance: float, port_clearance_mm: float | None,
                 off_command: bool) -> FilterOutput:
        """The FilterOutput of a solved step."""
        cutter = port_clearance_mm is not None and bool(port_clearance_mm > self.config.cutter_clearance_mm)
        intervened = bool(off_command or any(a.split(":", 1)[0] in self._intervening or a in RELAXATIONS
                                             for a in result.active))
        marks = tuple(a for a in result.active[:len(RELAXATIONS)] if a in RELAXATIONS)
        reason = ", ".join(marks) if marks else "ok"
        return FilterOutput(result.x, True, reason, result.active, float(clearance), cutter, intervened, result.solve_us)

    def row_names(self, ids, ranges) -> tuple:
        """The names of G's rows with identities `ids`."""
        return tuple(self.row_name(rid, ranges) for rid in ids.tolist())

    def row_name(self, rid: int, ranges) -> str:
        """The name of the row with identity `rid` (points per group: `ranges`)."""
        ci, local = self._id_owner[rid]
        c = self.constraints[ci]
        count = int(ranges[self.index[c.group], 1] - ranges[self.index[c.group], 0]) if c.group in self.index else 0
        return c.row_name(local, self._names(c.group, count) if c.group is not None else ())

    def active_names(self, ids, at_bound, ranges) -> tuple:
        """Sorted names of the rows at their bound, kept per (ids, rows at bound, ranges)."""
        key = (ids.tobytes(), at_bound.tobytes(), np.asarray(ranges).tobytes())
        names = self._names_cache.get(key)
        if names is None:
            rows = self.row_names(ids, ranges)
            names = tuple(sorted({rows[i] for i in at_bound.tolist()}))
            if len(self._names_cache) >= 4096:  # bounded: the combinations a run meets are few
                self._names_cache.clear()
            self._names_cache[key] = names
        return names

    def fault_reason(self, fault: int, detail: int, q, command, times, P, ranges) -> str:
        """Words for the step's fault code (step_core)."""
        cfg = self.config
        if fault in _FAULT_WORDS:
            return _FAULT_WORDS[fault]
        if fault == core.ABSURD_SPEED:
            speed = float(np.linalg.norm(command[:3]))
            return f"absurd command speed {speed:.1f} mm/s > {cfg.max_command_speed_mm_s:g} mm/s"
        if fault == core.STALE_MODEL:
            return f"stale model: {times[0] - times[1]:.3f} s old > {cfg.max_model_age_s:g} s"
        if fault == core.STALE_SENSOR:
            return f"stale sensor: {times[0] - times[2]:.3f} s old > {cfg.max_sensor_age_s:g} s"
        if fault == core.NONFINITE_POINTS:
            bad = np.flatnonzero(~np.all(np.isfinite(np.asarray(P).reshape(len(P), -1)), axis=1))
            k = int(bad[0]) if len(bad) else 0
            for g, (start, stop) in zip(self.groups, np.asarray(ranges).tolist()):
                if start <= k < stop:
                    return f"non-finite kinematics of {self._names(g, stop - start)[k - start]}"
            return "non-finite kinematics"
        if fault >= core.CONSTRAINT_FAULT:
            return self.constraints[fault - core.CONSTRAINT_FAULT].fault_reason(detail)
        return f"fault {fault}"


class RowNames(Sequence):
    """The names of G's rows with identities `ids` (ConstraintStack.row_name), each made when
    asked: a step the solver finishes names only its active rows (naming all ~30 was a fifth
    of such a step's time)."""

    def __init__(self, stack: ConstraintStack, ids: np.ndarray, ranges):
        self._stack, self._ids, self._ranges = stack, ids, np.array(ranges)

    def __len__(self) -> int:
        return len(self._ids)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return tuple(self[j] for j in range(*i.indices(len(self))))
        return self._stack.row_name(int(self._ids[i]), self._ranges)
