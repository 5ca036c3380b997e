"""The virtual boundary: a QP safety filter on commanded velocities that fails safe.

Each control step takes the commanded tip velocity and the robot's kinematics and
returns the joint velocities closest to the command that keep every monitored point
(tip, cutter port, shaft points inside the eye) at least `d_safe_mm` plus the model's
uncertainty inside the retina model, the shaft outside the lens keep-out, the RCM, and
the joint limits. On any fault (stale model or sensor, NaN, absurd command, infeasible
QP, solver failure) it commands zero velocity and says why: the robot stays put.

The rules are constraint objects (safety.constraints); `default_constraints` builds the
standard stack from a FilterConfig, and a ConstraintStack (safety.stack) compiles any
stack into one step. `SafetyFilter(config)(inputs)` is the stateless Python API on a
FilterInputs: it evaluates the model, the fallback and the lens in Python and runs the
same compiled step on the values.
"""
from __future__ import annotations

import numpy as np

from safety.constraints import (JointPositionLimits, JointSpeedLimits, KeepOut, LinearEquality, PointBarrier, RcmEquality,
                                TipSpeedLimit)
from safety.constraints.actuated_barrier import actuator_aware
from safety.inputs import FilterConfig, FilterInputs, FilterOutput, PointKinematics
from safety.stack import ConstraintStack
from safety.tabulated_field import tabulate, tabulated_kernel

ALWAYS_KEPT = ("tip", "port")  # their barrier rows are never screened out (the clearance and the cutter interlock)


def default_constraints(config: FilterConfig, q_min, q_max, qdot_max, retina_groups=(("boundary", "eye", 2),),
                        lens_group: tuple | None = ("lens", "lens"), rcm=None, extra=()) -> list:
    """The standard stack, in row order: tip speed, joint speed and position limits, one
    point barrier per (group, field slot, points always kept) of `retina_groups` (with the
    declared calibration bound in its margin: FilterConfig.calibration_margin_mm), the
    lens keep-out on (group, field slot) `lens_group`, the RCM constraint `rcm`, then `extra`."""
    reach = config.barrier_reach_mm  # what the speed limit closes at the barrier rate
    out = [TipSpeedLimit(config.max_tip_speed_mm_s), JointSpeedLimits(np.asarray(qdot_max, dtype=float)),
           JointPositionLimits(np.asarray(q_min, dtype=float), np.asarray(q_max, dtype=float), config.joint_gain_per_s,
                               config.joint_margin_rad)]
    for group, field, always in retina_groups:
        out.append(PointBarrier(group, field, config.d_safe_mm, config.gain_per_s, config.max_recovery_mm_s, reach,
                                always, config.sigma_factor, calibration_mm=config.calibration_margin_mm))
    if lens_group is not None:
        out.append(KeepOut(lens_group[0], lens_group[1], config.lens_margin_mm, config.gain_per_s,
                           config.max_recovery_mm_s, reach))
    if rcm is not None:
        out.append(rcm)
    return out + list(extra)


def rcm_constraint(config: FilterConfig, p_WC, gain_per_s: float) -> RcmEquality:
    """The RCM through the trocar p_WC (3,) mm, drift corrected at gain_per_s (1/s); its
    planned stop at the correction speed config's tip speed limit allows in every direction
    (safety.constraints.rcm: a growing correction the tip cannot follow leaves no velocity)."""
    return RcmEquality(np.asarray(p_WC, dtype=float), gain_per_s,
                       max_correction_mm_s=TipSpeedLimit(config.max_tip_speed_mm_s).every_direction_mm_s)


def _distance_and_gradient(shape, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(signed distance (M,) mm, gradient (M, 3)) of `shape` at P, in one query when the shape offers it."""
    if hasattr(shape, "signed_distance_and_gradient"):
        h, g = shape.signed_distance_and_gradient(P)
    else:
        h, g = shape.signed_distance(P), shape.gradient(P)
    return np.asarray(h, dtype=float), np.asarray(g, dtype=float)


class SafetyFilter:
    """`filter(inputs) -> FilterOutput`; stateless apart from its configuration and the
    compiled steps it keeps per stack layout. `extra`: constraints appended to the
    standard stack (their groups: "boundary", "lens"; their field slots: "eye", "lens")."""

    def __init__(self, config: FilterConfig | None = None, extra=()):
        self.config = FilterConfig() if config is None else config
        self.extra = tuple(extra)
        self._stacks: dict = {}

    def _constraints(self, x: FilterInputs, k: int, m: int) -> tuple[list, int]:
        """(the stack's constraints for these inputs, the boundary points always kept); their
        constructors' rules (joint limits, speed limits, the RCM's rows) raise ValueError."""
        always = 0
        while always < k and x.boundary_points[always].name in ALWAYS_KEPT:
            always += 1
        has_rcm = x.rcm_A is not None
        rcm = LinearEquality(np.atleast_2d(x.rcm_A), np.atleast_1d(x.rcm_b), refusal=x.rcm_refusal,
                             drift_correction=True) if has_rcm else None  # the RCM's b: its correction
        constraints = default_constraints(self.config, x.q_min, x.q_max, x.qdot_max, (("boundary", "eye", always),),
                                          ("lens", "lens") if m else None, rcm, self.extra)
        if x.pending is not None:  # the actuator the inputs describe
            constraints = actuator_aware(constraints)
        return constraints, always

    def _stack(self, x: FilterInputs, constraints: list, always: int, n: int, k: int, m: int) -> ConstraintStack:
        key = (n, k, m, always, tuple(c.key() for c in constraints),
               tuple(c.max_rows(0) for c in constraints if c.kind == "equality"))
        stack = self._stacks.get(key)
        if stack is None:
            names = {"boundary": tuple(p.name for p in x.boundary_points), "lens": tuple(p.name for p in x.lens_points)}
            port = next((i for i, p in enumerate(x.boundary_points) if p.name == "port"), None)
            stack = ConstraintStack(constraints, {"boundary": k, "lens": m}, {"eye": tabulated_kernel,
                                                                              "lens": tabulated_kernel},
                                    self.config, point_names=lambda g, c: names[g][:c],
                                    port=None if port is None else ("boundary", port), n_joints=n)
            self._stacks[key] = stack
        stack.set_params(constraints)  # this call's numbers, the layout compiled once
        return stack

    def __call__(self, x: FilterInputs) -> FilterOutput:
        return self._run(x)[0]

    def qp(self, x: FilterInputs):
        """The step's QP (safety.qp.DenseQP) for these inputs, as the filter builds it (None on a fault)."""
        out, stack, r, ranges = self._run(x)
        return None if stack is None else stack.qp(r, ranges)

    def _run(self, x: FilterInputs) -> tuple:
        """(FilterOutput, the stack, its raw result, the point ranges); None for the last three
        on a fault found before the compiled step."""
        n = len(np.atleast_1d(x.q))
        fault = self._fault(x, n)
        if not fault:
            pts = list(x.boundary_points)
            lens_pts = list(x.lens_points) if x.lens is not None else []
            k, m = len(pts), len(lens_pts)
            try:  # the constraints' own rules on their numbers (one definition: their constructors)
                constraints, always = self._constraints(x, k, m)
            except ValueError as e:
                fault = f"invalid inputs: {e}"
        if fault:
            return FilterOutput(np.zeros(n), False, fault), None, None, None
        P = np.array([p.p_W for p in pts + lens_pts], dtype=float).reshape(k + m, 3)
        J = np.array([p.J_W for p in pts + lens_pts], dtype=float).reshape(k + m, 3, n)
        u = float(x.margin_mm) + np.array([p.margin_mm for p in pts], dtype=float)
        fields = {"eye": tabulate(np.nan, np.full(3, np.nan), np.nan) if k else np.zeros(0), "lens": np.zeros(0)}
        if np.isfinite(P).all():  # else the compiled step names the point (non-finite kinematics)
            h, g = _distance_and_gradient(x.model, P[:k])
            untrusted = [i for i, p in enumerate(pts) if not p.trusted]
            if untrusted and x.fallback is not None:  # the tighter of the model and the fallback
                h_f, g_f = _distance_and_gradient(x.fallback, P[untrusted])
                tighter = ~(h_f >= h[untrusted])  # a NaN fallback counts: the step then faults on it
                rows = np.asarray(untrusted)[tighter]
                h[rows], g[rows] = h_f[tighter], g_f[tighter]
            fields["eye"] = tabulate(h, g, u)
            if m:
                fields["lens"] = tabulate(*_distance_and_gradient(x.lens, P[k:]), np.zeros(m))
        stack = self._stack(x, constraints, always, n, k, m)
        J_roll = np.zeros((0, n)) if x.J_roll is None else np.atleast_2d(np.asarray(x.J_roll, dtype=float))
        command = np.concatenate([np.asarray(x.v_cmd_W, dtype=float), [float(x.roll_rate_cmd)]])
        ranges = np.array([[0, k], [k, k + m]], dtype=np.int64)
        times = np.array([x.t_s, x.model_time_s, x.sensor_time_s], dtype=float)
        pending = None if x.pending is None else np.ascontiguousarray(np.asarray(x.pending, dtype=float).reshape(-1, n))
        out, r = stack.solve(np.asarray(x.q, dtype=float), command, times, np.asarray(x.J_tip, dtype=float), J_roll, P,
                             J, ranges, tuple(fields[s] for s in stack.slots), pending=pending)
        return out, stack, r, ranges

    def _fault(self, x: FilterInputs, n: int) -> str | None:
        """Why this step must not move the robot, from the inputs' structure, or None: the
        constraints' constructors check their own numbers (_constraints) and the compiled
        step the rest (non-finite numbers, the command's speed, the ages), each in its words."""
        if np.shape(x.J_tip) != (3, n):
            return f"J_tip has shape {np.shape(x.J_tip)}, expected (3, {n})"
        if np.shape(x.v_cmd_W) != (3,):
            return f"v_cmd_W has shape {np.shape(x.v_cmd_W)}, expected (3,)"
        for name in ("q_min", "q_max", "qdot_max"):
            if np.shape(getattr(x, name)) != (n,):
                return f"{name} has shape {np.shape(getattr(x, name))}, expected ({n},)"
        if x.J_roll is not None and np.atleast_2d(x.J_roll).shape[1:] != (n,):
            return f"J_roll has shape {np.shape(x.J_roll)}, expected (r, {n})"
        if not x.boundary_points:
            return "no boundary points"
        for p in list(x.boundary_points) + (list(x.lens_points) if x.lens is not None else []):
            if not isinstance(p, PointKinematics):
                return f"a monitored point is a {type(p).__name__}, not a PointKinematics"
            if np.shape(p.p_W) != (3,) or np.shape(p.J_W) != (3, n):
                return f"point {p.name}: p_W {np.shape(p.p_W)} and J_W {np.shape(p.J_W)}, expected (3,) and (3, {n})"
        if x.pending is not None and (np.ndim(x.pending) != 2 or np.shape(x.pending)[1] != n):
            return f"pending has shape {np.shape(x.pending)}, expected (r, {n})"
        if x.model is None:
            return "no eye model"
        if not (np.isfinite(x.margin_mm) and x.margin_mm >= 0):
            return f"invalid margin {x.margin_mm}"
        bad = next((p for p in x.boundary_points if not (np.isfinite(p.margin_mm) and p.margin_mm >= 0)), None)
        if bad is not None:
            return f"invalid margin {bad.margin_mm} of {bad.name}"
        return None
