"""The virtual boundary: a QP safety filter on commanded velocities that fails safe.

Each control step takes the commanded tip velocity and the robot's kinematics at the
current joint angles and returns the joint velocities closest to the command that keep
every monitored point (tip, cutter port, shaft points inside the eye) at least
`d_safe_mm` (+ the model's uncertainty margin) inside the retina model, the shaft
outside the lens keep-out, the RCM, and the joint limits. On any fault (stale model or
sensor, NaN, absurd command, infeasible QP, solver failure) it commands zero velocity
and says why: the robot stays put.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numba import njit

from safety import constraints
from safety.qp import solve


@dataclass(frozen=True)
class FilterConfig:
    """Filter parameters (mm, s, rad). `gain_per_s`: barrier rate (gain x dt must stay
    well below 1 at the control rate); `damping`: (mm/rad)^2 weight on |qdot|^2."""

    d_safe_mm: float = 0.5
    gain_per_s: float = 20.0
    lens_margin_mm: float = 0.3
    joint_gain_per_s: float = 10.0
    joint_margin_rad: float = np.radians(2.0)
    max_tip_speed_mm_s: float = 20.0
    max_command_speed_mm_s: float = 200.0
    damping: float = 1e-3
    max_model_age_s: float = 0.1
    max_sensor_age_s: float = 0.05
    cutter_clearance_mm: float = 1.0
    max_recovery_mm_s: float = 5.0
    solver: str = "daqp"  # fastest on this QP (bench_safety); "clarabel" also works

    def __post_init__(self):
        for name in ("d_safe_mm", "gain_per_s", "joint_gain_per_s", "max_tip_speed_mm_s", "max_command_speed_mm_s",
                     "max_model_age_s", "max_sensor_age_s", "cutter_clearance_mm", "max_recovery_mm_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"FilterConfig.{name} must be finite and > 0, got {v}")
        for name in ("lens_margin_mm", "joint_margin_rad", "damping"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"FilterConfig.{name} must be finite and >= 0, got {v}")


@dataclass(frozen=True, eq=False)
class PointKinematics:
    """A monitored point: name, position p_W (3,) mm, translational Jacobian J_W (3, n)
    mm/rad; `trusted` False where the model has no data near the point (then the
    inputs' `fallback` shape bounds it too); `margin_mm` extra clearance for this point
    (e.g. the model's measured local misfit near it)."""

    name: str
    p_W: np.ndarray
    J_W: np.ndarray
    trusted: bool = True
    margin_mm: float = 0.0


@dataclass(frozen=True, eq=False)
class FilterInputs:
    """One control step's inputs (mm, s, rad; W frame).

    `boundary_points` must stay inside the retina model, `lens_points` outside the lens
    keep-out; `rcm_A qdot = rcm_b` are the RCM rows; `model` answers signed_distance and
    gradient (> 0 inside); `margin_mm` is added to d_safe (model uncertainty);
    `model_time_s` / `sensor_time_s` are the times of the last model update and sensor
    sample, checked against `t_s`. `fallback` (a shape inside every plausible retina,
    e.g. the conservative prior) bounds the boundary points marked untrusted: their
    clearance is the smaller of the model's and the fallback's.
    """

    t_s: float
    q: np.ndarray
    q_min: np.ndarray
    q_max: np.ndarray
    qdot_max: np.ndarray
    v_cmd_W: np.ndarray
    J_tip: np.ndarray
    boundary_points: list
    model: object
    model_time_s: float
    sensor_time_s: float
    rcm_A: np.ndarray | None = None
    rcm_b: np.ndarray | None = None
    lens: object = None
    lens_points: list = field(default_factory=list)
    margin_mm: float = 0.0
    J_roll: np.ndarray | None = None
    roll_rate_cmd: float = 0.0
    fallback: object = None


class FilterOutput(NamedTuple):
    """`qdot` (n,) rad/s to command (zeros on a fault); `ok` False on a fault, with
    `reason`; `active`: names of the constraints at their bound; `min_clearance_mm`: the
    smallest model clearance of the boundary points minus d_safe-free (mm);
    `cutter_allowed`: the port's clearance exceeds the interlock threshold;
    `intervened`: the output departs from the command (an active constraint, or a tip
    velocity off the command by more than 1 %). A NamedTuple: one is made per control
    step, so it must be cheap."""

    qdot: np.ndarray
    ok: bool
    reason: str
    active: tuple = ()
    min_clearance_mm: float = float("nan")
    cutter_allowed: bool = False
    intervened: bool = True
    solve_us: float = 0.0


@njit(cache=True)
def _off_command(J_tip, qdot, v_cmd) -> bool:
    """The tip velocity J_tip qdot (mm/s) is off the command v_cmd by more than 1 % of its speed."""
    err2, speed2 = 0.0, 0.0
    for r in range(3):
        v = 0.0
        for j in range(qdot.shape[0]):
            v += J_tip[r, j] * qdot[j]
        err2 += (v - v_cmd[r]) ** 2
        speed2 += v_cmd[r] ** 2
    return np.sqrt(err2) > 0.01 * max(np.sqrt(speed2), 1e-9)


def _distance_and_gradient(shape, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(signed distance (M,) mm, gradient (M, 3)) of `shape` at P, in one query when the
    shape offers it."""
    if hasattr(shape, "signed_distance_and_gradient"):
        h, g = shape.signed_distance_and_gradient(P)
    else:
        h, g = shape.signed_distance(P), shape.gradient(P)
    return np.asarray(h, dtype=float), np.asarray(g, dtype=float)


class SafetyFilter:
    """`filter(inputs) -> FilterOutput`; stateless apart from its configuration."""

    def __init__(self, config: FilterConfig | None = None):
        self.config = FilterConfig() if config is None else config

    def _stop(self, n: int, reason: str, clearance=float("nan")) -> FilterOutput:
        return FilterOutput(np.zeros(n), False, reason, min_clearance_mm=clearance)

    def __call__(self, x: FilterInputs) -> FilterOutput:
        cfg = self.config
        n = len(np.atleast_1d(x.q))
        pts = x.boundary_points
        lens_pts = x.lens_points if x.lens is not None else []
        fault = self._fault(x, n)
        if fault:
            return self._stop(n, fault)
        P = np.array([p.p_W for p in pts + lens_pts], dtype=float)
        J = np.array([p.J_W for p in pts + lens_pts], dtype=float)
        if not (np.isfinite(P).all() and np.isfinite(J).all()):
            bad = next(p for p in pts + lens_pts if not (np.all(np.isfinite(p.p_W)) and np.all(np.isfinite(p.J_W))))
            return self._stop(n, f"non-finite kinematics of {bad.name}")
        k = len(pts)
        h_model, g_model = _distance_and_gradient(x.model, P[:k])
        h_fallback, g_fallback = np.full(k, np.inf), np.zeros((k, 3))
        untrusted = [i for i, p in enumerate(pts) if not p.trusted]
        if untrusted and x.fallback is not None:  # the tighter of the model and the fallback
            h_fallback[untrusted], g_fallback[untrusted] = _distance_and_gradient(x.fallback, P[untrusted])
        h_lens, g_lens = _distance_and_gradient(x.lens, P[k:]) if lens_pts else (np.zeros(0), np.zeros((0, 3)))
        h, grad, h_min, keep, finite = constraints.barrier_rows(
            h_model, g_model, h_fallback, g_fallback, np.array([p.margin_mm for p in pts], dtype=float),
            float(x.margin_mm), cfg.d_safe_mm, np.array([p.name in ("tip", "port") for p in pts]), h_lens, g_lens,
            cfg.lens_margin_mm, cfg.max_tip_speed_mm_s / cfg.gain_per_s)
        if not finite:
            return self._stop(n, "model returned non-finite distance or gradient")
        clearance = float(h[:k].min())
        names = [f"boundary:{p.name}" for p in pts] + [f"lens:{p.name}" for p in lens_pts]
        rows = np.flatnonzero(keep)
        qp = constraints.filter_qp(
            x.J_tip, x.v_cmd_W, cfg.damping, x.J_roll, x.roll_rate_cmd, x.q, x.q_min, x.q_max, x.qdot_max,
            cfg.joint_gain_per_s, cfg.joint_margin_rad, cfg.max_tip_speed_mm_s, tuple(names[i] for i in rows), h[rows],
            grad[rows], J[rows], h_min[rows], cfg.gain_per_s, cfg.max_recovery_mm_s, x.rcm_A, x.rcm_b)
        result = solve(qp, cfg.solver)
        if not result.ok:
            return self._stop(n, f"QP: {result.reason}", clearance)
        port = [hi for p, hi in zip(pts, h) if p.name == "port"]
        off = _off_command(np.asarray(x.J_tip, dtype=float), result.x, np.asarray(x.v_cmd_W, dtype=float))
        return self.output(result, clearance, port[0] if port else None, off)

    def output(self, result, clearance: float, port_clearance_mm: float | None, off_command: bool) -> FilterOutput:
        """The FilterOutput of a solved step: `result` (safety.qp.QPResult, ok), the smallest
        clearance (mm), the port's (mm, None without a port) for the cutter interlock, and
        whether the tip velocity is off the command by > 1 % (_off_command)."""
        cutter = port_clearance_mm is not None and bool(port_clearance_mm > self.config.cutter_clearance_mm)
        intervened = bool(off_command or any(a.startswith(("boundary", "lens", "tip_speed")) for a in result.active))
        return FilterOutput(result.x, True, "ok", result.active, clearance, cutter, intervened, result.solve_us)

    def _fault(self, x: FilterInputs, n: int) -> str | None:
        """Why this step must not move the robot, or None."""
        cfg = self.config
        arrays = {"q": x.q, "v_cmd_W": x.v_cmd_W, "J_tip": x.J_tip}
        if not math.isfinite(sum(float(np.sum(a)) for a in arrays.values())):  # one pass; names on failure
            bad = next((name for name, a in arrays.items() if not np.all(np.isfinite(a))), None)
            if bad is not None:
                return f"non-finite {bad}"
        if np.shape(x.J_tip) != (3, n):
            return f"J_tip has shape {np.shape(x.J_tip)}, expected (3, {n})"
        if not x.boundary_points:
            return "no boundary points"
        speed = float(np.linalg.norm(x.v_cmd_W))
        if speed > cfg.max_command_speed_mm_s:
            return f"absurd command speed {speed:.1f} mm/s > {cfg.max_command_speed_mm_s:g} mm/s"
        if x.model is None:
            return "no eye model"
        if not (x.t_s - x.model_time_s <= cfg.max_model_age_s):
            return f"stale model: {x.t_s - x.model_time_s:.3f} s old > {cfg.max_model_age_s:g} s"
        if not (x.t_s - x.sensor_time_s <= cfg.max_sensor_age_s):
            return f"stale sensor: {x.t_s - x.sensor_time_s:.3f} s old > {cfg.max_sensor_age_s:g} s"
        if not (np.isfinite(x.margin_mm) and x.margin_mm >= 0):
            return f"invalid margin {x.margin_mm}"
        bad = next((p for p in x.boundary_points if not (math.isfinite(p.margin_mm) and p.margin_mm >= 0)), None)
        if bad is not None:
            return f"invalid margin {bad.margin_mm} of {bad.name}"
        return None
