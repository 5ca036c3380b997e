"""Spiral scan execution through the trocar: IK waypoints + time parameterisation, and
RCM differential kinematics at 1 kHz as a second executor.

Units: mm, s, rad; tip speed mm/s; errors reported in um and margins in deg where named.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from pydrake.trajectories import PiecewisePolynomial

from models.shapes.validation import as_positive
from planning.closed_form import shaft_ik
from planning.diffik import rcm_joint_velocity
from planning.ik import IKFailure, has_roll, rcm_ik, roll_direction_W, signed_angle
from planning.robot import RCM_GAIN_PER_S, Robot

SPEED_HEADROOM = 0.9  # time parameterisation keeps every joint below this fraction of its limit
TRACKING_GAIN_PER_S = 20.0  # tip position feedback of the differential-kinematics executor
MIDPOINT_ROUNDS = 8  # plan_ik_scan halves a segment that leaves the RCM at most this often (1/256 of it)


@dataclass(frozen=True)
class ScanRun:
    """One executed scan sampled at `rate_hz`: times t (M,) s, joint angles q (M, 6) rad,
    joint velocities qdot (M, 6) rad/s, RCM error (M,) um and tip error to the reference
    (M,) um. `solve_ms` is the mean planning time per waypoint (IK) or per step."""

    t: np.ndarray
    q: np.ndarray
    qdot: np.ndarray
    rcm_error_um: np.ndarray
    tip_error_um: np.ndarray
    solve_ms: float

    def figures(self, robot: Robot) -> dict:
        """The scan.json figures: RCM error, joint margins, speed fraction, duration."""
        margin_deg = np.degrees(np.minimum(self.q - robot.q_lower, robot.q_upper - self.q))
        speed = np.abs(self.qdot) / robot.qdot_max
        return {
            "max_rcm_error_um": float(self.rcm_error_um.max()),
            "mean_rcm_error_um": float(self.rcm_error_um.mean()),
            "min_joint_margin_deg": float(margin_deg.min()),
            "max_joint_speed_fraction": float(speed.max()),
            "duration_s": float(self.t[-1] - self.t[0]),
            "min_joint_margin_deg_per_joint": [float(v) for v in margin_deg.min(axis=0)],
            "max_joint_speed_fraction_per_joint": [float(v) for v in speed.max(axis=0)],
            "max_tip_error_um": float(self.tip_error_um.max()),
            "solve_ms_mean": float(self.solve_ms),
        }


def start_posture(robot: Robot, p_WT, p_WC) -> np.ndarray:
    """(6,) rad: the RCM posture at the first target on the closed-form branch with the
    largest smallest joint margin (J6 = 0), refined by the Drake IK."""
    p_T, p_C = np.asarray(p_WT, dtype=float), np.asarray(p_WC, dtype=float)
    cands = shaft_ik(robot.arm, p_T, (p_T - p_C) / np.linalg.norm(p_T - p_C))
    if not len(cands):
        raise IKFailure(f"tip target p_WT_mm = {np.round(p_T, 3)} is out of the arm's reach through p_WC_mm = {np.round(p_C, 3)}")
    margins = np.minimum(cands - robot.q_lower, robot.q_upper - cands).min(axis=1)
    return rcm_ik(robot, p_T, p_C, cands[np.argmax(margins)])


def ik_waypoints(robot: Robot, P_WT, p_WC, q_start=None, roll_rad=None) -> tuple[np.ndarray, float]:
    """((N, 6) rad joint waypoints for the tip targets P_WT (N, 3) mm through the trocar,
    each IK seeded from the previous solution, with the roll about the shaft `roll_rad`
    (N,) when given (planning.ik.roll_direction_W); mean solve time in ms). Raises
    IKFailure naming the first unreachable target before anything is returned."""
    P = np.asarray(P_WT, dtype=float)
    roll = [None] * len(P) if roll_rad is None else list(np.asarray(roll_rad, dtype=float))
    q = start_posture(robot, P[0], p_WC) if q_start is None else q_start
    q = rcm_ik(robot, P[0], p_WC, q, roll_rad=roll[0]) if (q_start is not None or roll[0] is not None) else q
    Q = np.empty((len(P), 6))
    Q[0] = q
    t0 = time.perf_counter()
    for i in range(1, len(P)):
        Q[i] = q = rcm_ik(robot, P[i], p_WC, q, roll_rad=roll[i])
    return Q, (time.perf_counter() - t0) * 1e3 / max(len(P) - 1, 1)


def waypoint_times(robot: Robot, Q, P_WT, tip_speed_mm_s: float) -> np.ndarray:
    """(N,) s: times at which the tip passes the waypoints at `tip_speed_mm_s` along the
    path, each segment stretched where a joint would exceed SPEED_HEADROOM of its limit."""
    v = as_positive(tip_speed_mm_s, "tip_speed_mm_s")
    dt_tip = np.linalg.norm(np.diff(np.asarray(P_WT, dtype=float), axis=0), axis=1) / v
    dt_joint = (np.abs(np.diff(Q, axis=0)) / (SPEED_HEADROOM * robot.qdot_max)).max(axis=1)
    return np.concatenate([[0.0], np.cumsum(np.maximum(dt_tip, dt_joint))])


def waypoint_velocities(t, Q) -> np.ndarray:
    """(N, 6) rad/s: the joints' velocity at each waypoint of Q (N, 6) rad at times t (N,) s,
    at rest at both ends. Inside, the mean of the two adjacent secants, each weighted by
    the other segment's duration (Bessel's three-point derivative), scaled down, all joints
    by one factor, until no joint's exceeds three times the smaller of its two secants
    where they agree in sign (Fritsch & Carlson, SIAM J. Numer. Anal. 17, 1980: the bound
    under which a cubic Hermite segment stays monotone between monotone data). Linear in
    the secants and scaled as one vector, each is a velocity of the RCM-constrained motion
    to first order, as the waypoints' secants are; per-joint limiting (Fritsch & Carlson's
    own slopes, Drake's CubicShapePreserving) is not: on the peripheral plan's sweep it left
    the RCM 20 um off where the tip path turns a corner."""
    t, Q = np.asarray(t, dtype=float), np.asarray(Q, dtype=float)
    if t.ndim != 1 or Q.shape != (len(t), 6) or len(t) < 2:
        raise ValueError(f"waypoint_velocities: t must be (N,) s and Q (N, 6) rad with N >= 2, got {t.shape} and {Q.shape}")
    if not (np.isfinite(t).all() and np.isfinite(Q).all()):
        raise ValueError("waypoint_velocities: t and Q must be finite")
    if not np.all(np.diff(t) > 0.0):
        raise ValueError("waypoint_velocities: the times t must increase strictly (s)")
    h = np.diff(t)[:, None]
    s = np.diff(Q, axis=0) / h
    V = np.zeros_like(Q)
    if len(Q) > 2:
        m = (h[1:] * s[:-1] + h[:-1] * s[1:]) / (h[:-1] + h[1:])
        bound = 3.0 * np.minimum(np.abs(s[:-1]), np.abs(s[1:]))
        limited = (s[:-1] * s[1:] > 0.0) & (np.abs(m) > bound)
        scale = np.where(limited, bound / np.where(limited, np.abs(m), 1.0), 1.0).min(axis=1, keepdims=True)
        V[1:-1] = scale * m
    return V


def joint_trajectory(robot: Robot, Q, P_WT, tip_speed_mm_s: float) -> PiecewisePolynomial:
    """q(t) rad: the cubic Hermite curve through the waypoints Q (N, 6) with the velocities
    of `waypoint_velocities` (local: a segment depends on its two neighbours only), starting
    and ending at rest, timed by `waypoint_times`; globally slowed until its joint speeds
    (sampled at the waypoints and mid-segments) stay below SPEED_HEADROOM of the limits.
    The C2 cubic spline through the same waypoints couples every segment and swings joints
    past the waypoints' range: on the detached eye's local plan at 2.0 mm (seed 0) the
    filter then stepped in on 0.68 % of the steps (the sweeps' 0.70 %, mostly at joint
    bounds) and shaved 84.4 % of the band."""
    t = waypoint_times(robot, Q, P_WT, tip_speed_mm_s)
    for _ in range(20):
        traj = PiecewisePolynomial.CubicHermite(t, Q.T, waypoint_velocities(t, Q).T)
        ts = np.sort(np.concatenate([t, 0.5 * (t[1:] + t[:-1])]))
        peak = (np.abs(traj.derivative(1).vector_values(ts)).T / robot.qdot_max).max()
        if peak <= SPEED_HEADROOM:
            return traj
        t = t * (peak / SPEED_HEADROOM) * 1.01
    raise ValueError(f"tip_speed_mm_s = {tip_speed_mm_s}: no timing keeps the joints within their speed limits")


def plan_ik_scan(robot: Robot, P_WT, p_WC, tip_speed_mm_s: float, q_start=None,
                 tol_um: float = 0.5, roll_rad=None, Q_waypoints=None,
                 midpoints: dict | None = None) -> tuple[PiecewisePolynomial, np.ndarray, float]:
    """(q(t), the tip targets used (K, 3) mm, mean IK time per waypoint in ms) for the
    targets P_WT (N, 3) mm (optional rolls `roll_rad` (N,)): IK waypoints, then wherever
    the spline between two waypoints leaves the RCM or the straight tip segment by more
    than `tol_um` (checked at quarter points) the midpoint target is added by IK too (at
    most MIDPOINT_ROUNDS rounds: fast joint swings, as next to the trocar, need denser
    waypoints; with rolls given, a midpoint takes the roll of its neighbours' mean posture
    (posture_roll_rad: J6 turns on evenly between them, where the rolls' mean can lie half
    a turn off it between cells far apart), or, where that is out of the wrist's range,
    the roll nearest that posture (the port faces the retina at the cells; without such a
    midpoint the curve across the segment leaves the RCM: 1.0 mm on the detached eye's
    plan at 2.3 mm); a midpoint out of reach, on a chord across a gap of the workspace, is
    left out and its segment kept as the spline makes it). `Q_waypoints` (N, 6): the
    waypoints' IK already solved by the caller (then not solved again).
    `midpoints`: a dict the caller keeps across calls on overlapping targets (a sweep
    re-timed after dropping cells), holding each midpoint's IK by its target, roll and
    seed (None: out of reach); the same inputs, the same answer, solved once."""
    P = np.asarray(P_WT, dtype=float)
    roll = None if roll_rad is None else np.asarray(roll_rad, dtype=float)
    if Q_waypoints is None:
        Q, solve_ms = ik_waypoints(robot, P, p_WC, q_start, roll)
    else:
        Q, solve_ms = np.array(Q_waypoints, dtype=float), float("nan")
    solved = {} if midpoints is None else midpoints  # (target, roll, seed) -> posture, None out of reach
    for _ in range(MIDPOINT_ROUNDS):
        traj = joint_trajectory(robot, Q, P, tip_speed_mm_s)
        t = np.asarray(traj.get_segment_times())
        ts = (t[:-1, None] + np.array([0.25, 0.5, 0.75]) * np.diff(t)[:, None]).ravel()
        qs = traj.vector_values(ts).T
        rcm = np.array([robot.rcm_error_mm(qi, p_WC) for qi in qs])
        tip = np.array([robot.point("T", np.zeros(3), qi) for qi in qs])
        A, AB = np.repeat(P[:-1], 3, axis=0), np.repeat(np.diff(P, axis=0), 3, axis=0)
        u = np.clip(((tip - A) * AB).sum(axis=1) / np.maximum((AB * AB).sum(axis=1), 1e-18), 0.0, 1.0)
        off = np.linalg.norm(A + u[:, None] * AB - tip, axis=1)
        err = np.maximum(rcm, off).reshape(-1, 3).max(axis=1)
        bad = np.flatnonzero(err * 1e3 > tol_um)
        if not bad.size:
            break
        mids = 0.5 * (P[bad] + P[bad + 1])
        added = []
        for m, i in zip(mids, bad):
            seed = 0.5 * (Q[i] + Q[i + 1])
            # a midpoint whose shaft is vertical has no roll: IK from the neighbours' mean posture
            mid_roll = posture_roll_rad(robot, seed, m, p_WC) if roll is not None and has_roll(m, p_WC) else None
            key = (m.tobytes(), None if mid_roll is None else float(mid_roll), seed.tobytes())
            if key not in solved:
                solved[key] = _midpoint_posture(robot, m, p_WC, seed, mid_roll)
            if solved[key] is not None:
                added.append((i, m, solved[key]))
        if not added:
            break
        at = np.array([a[0] for a in added]) + 1
        P = np.insert(P, at, np.array([a[1] for a in added]), axis=0)
        Q = np.insert(Q, at, np.array([a[2] for a in added]), axis=0)
    return joint_trajectory(robot, Q, P, tip_speed_mm_s), P, solve_ms


def posture_roll_rad(robot: Robot, q, p_WT, p_WC) -> float:
    """The roll (rad, planning.ik.roll_direction_W) about the shaft from the trocar p_WC to
    the tip target p_WT (mm, W) nearest the instrument's at the posture q (6,) rad: its y
    axis turned about the shaft onto the plane normal to it. J6 turns the instrument about
    that axis, so at the mean of two postures' joints it lies where J6 is their mean."""
    p_WT, p_WC = np.asarray(p_WT, dtype=float), np.asarray(p_WC, dtype=float)
    u = (p_WT - p_WC) / np.linalg.norm(p_WT - p_WC)
    y = robot.pose("I", q)[0][:, 1]
    return signed_angle(roll_direction_W(p_WT, p_WC, 0.0), y - (y @ u) * u, u)


def _midpoint_posture(robot: Robot, p_WT, p_WC, seed, roll_rad):
    """A midpoint's posture: at `roll_rad`, else (out of the wrist's range there) at the
    roll nearest `seed`, the neighbours' mean posture (the port faces the retina at the
    cells, not between them); None when the midpoint itself is out of reach (a chord over
    a gap of the workspace: the caller keeps the segment)."""
    for roll in dict.fromkeys((roll_rad, None)):
        try:
            return rcm_ik(robot, p_WT, p_WC, seed, roll_rad=roll)
        except IKFailure:
            pass
    return None


def sample_ik_run(robot: Robot, traj: PiecewisePolynomial, P_WT, p_WC, tip_speed_mm_s: float,
                  rate_hz: float = 1000.0, solve_ms: float = float("nan")) -> ScanRun:
    """The IK executor's scan sampled at `rate_hz`: the trajectory, its RCM error and the
    tip's distance from the polyline of targets (um)."""
    t = np.arange(traj.start_time(), traj.end_time(), 1.0 / rate_hz)
    t = np.append(t, traj.end_time())
    q = traj.vector_values(t).T
    qdot = traj.derivative(1).vector_values(t).T
    rcm = np.array([robot.rcm_error_mm(qi, p_WC) for qi in q]) * 1e3
    tips = np.array([robot.point("T", np.zeros(3), qi) for qi in q])
    return ScanRun(t, q, qdot, rcm, _distance_to_polyline(tips, np.asarray(P_WT, dtype=float)) * 1e3, solve_ms)


def run_diffik(robot: Robot, P_WT, p_WC, q_start, tip_speed_mm_s: float, rate_hz: float = 1000.0,
               rcm_gain_per_s: float = RCM_GAIN_PER_S) -> ScanRun:
    """The differential-kinematics executor: the tip reference moves along the targets
    P_WT (N, 3) mm at `tip_speed_mm_s`; each step commands its velocity plus position
    feedback, solves the RCM-constrained differential kinematics, scales the joint
    velocity uniformly to the speed limits and integrates with explicit Euler at `rate_hz`."""
    v = as_positive(tip_speed_mm_s, "tip_speed_mm_s")
    dt = 1.0 / as_positive(rate_hz, "rate_hz")
    P = np.asarray(P_WT, dtype=float)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    n = int(np.ceil(s[-1] / v / dt)) + 1
    t = np.arange(n) * dt
    ref = np.column_stack([np.interp(np.minimum(t * v, s[-1]), s, P[:, k]) for k in range(3)])
    v_ff = np.vstack([np.diff(ref, axis=0) / dt, np.zeros((1, 3))])
    q = np.asarray(q_start, dtype=float).copy()
    Q, QD, rcm, tip = np.empty((n, 6)), np.empty((n, 6)), np.empty(n), np.empty(n)
    t0 = time.perf_counter()
    for k in range(n):
        p_T = robot.point("T", np.zeros(3), q)
        tip[k] = np.linalg.norm(p_T - ref[k])
        rcm[k] = robot.rcm_error_mm(q, p_WC)
        qd = rcm_joint_velocity(robot, q, v_ff[k] + TRACKING_GAIN_PER_S * (ref[k] - p_T), p_WC, rcm_gain_per_s)
        qd /= max(1.0, (np.abs(qd) / robot.qdot_max).max())
        Q[k], QD[k] = q, qd
        q = q + dt * qd
    solve_ms = (time.perf_counter() - t0) * 1e3 / n
    return ScanRun(t, Q, QD, rcm * 1e3, tip * 1e3, solve_ms)


def _distance_to_polyline(X, P) -> np.ndarray:
    """(M,) distance (mm) of each point X (M, 3) from the polyline through P (N, 3),
    searched near the point's place along the path (both advance monotonically)."""
    A, B = P[:-1], P[1:]
    AB = B - A
    L2 = np.maximum((AB * AB).sum(axis=1), 1e-18)
    out = np.empty(len(X))
    j = 0
    for i, x in enumerate(X):
        lo, hi = max(j - 5, 0), min(j + 200, len(A))
        u = np.clip(((x - A[lo:hi]) * AB[lo:hi]).sum(axis=1) / L2[lo:hi], 0.0, 1.0)
        d = np.linalg.norm(A[lo:hi] + u[:, None] * AB[lo:hi] - x, axis=1)
        k = int(np.argmin(d))
        out[i], j = d[k], lo + k
    return out
