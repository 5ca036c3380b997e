"""One trocar's shaving sweep over band cells (planning.peripheral): RCM IK with the
cutter port turned to the retina, timed within the joint speed limits, the shaft checked
against the boundary at each cell and along the timed path. Units: mm, s, rad; frame W.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.trajectories import PiecewisePolynomial

from planning.closed_form import shaft_ik
from planning.ik import IKFailure, rcm_ik, roll_direction_W, signed_angle
from planning.instrument_points import instrument_points
from planning.robot import Robot
from planning.scan import plan_ik_scan, start_posture
from planning.scenario import LENS_CLEARANCE_MM

SHAFT_SLACK_MM = 0.2  # monitored points plan this far outside the boundary (the filter stays out)
MAX_JOINT_STEP_RAD = 1.0  # between neighbouring cells (1 mm apart): more is a branch change
SHAFT_CHECK_DT_S = 0.005  # the timed path's shaft check: the shaft moves < 0.05 mm between samples at 10 mm/s
CHORD_STEP_MM = 0.25  # the first look's samples on the tip's segment between cells


def port_roll_rad(p_WT: np.ndarray, p_WC: np.ndarray, normal_in_W: np.ndarray) -> float:
    """Roll about the shaft (planning.ik.roll_direction_W convention) that turns the
    cutter port (on the instrument's -y side) toward the retina (outward normal).
    ValueError for a shaft within 1 deg of vertical, where the convention has no roll."""
    u = (p_WT - p_WC) / np.linalg.norm(p_WT - p_WC)
    h = roll_direction_W(p_WT, p_WC, 0.0)
    out = -normal_in_W
    m = out - (out @ u) * u
    y = -m / np.linalg.norm(m)  # the port is at -y: y points away from the retina
    return signed_angle(h, y, u)


def lens_clearances_mm(lens_W, p_WC, P_WT, samples: int = 32) -> np.ndarray:
    """(M,) smallest distance (mm, < 0: crossing) outside the lens keep-out `lens_W` (a
    shape in W, signed distance > 0 inside) of the straight shaft from the trocar p_WC (3,)
    to each tip P_WT (M, 3) mm, sampled."""
    s = np.linspace(0.0, 1.0, samples)[None, :, None]
    P = np.atleast_2d(np.asarray(P_WT, dtype=float))
    seg = np.asarray(p_WC, dtype=float) + s * (P[:, None, :] - np.asarray(p_WC, dtype=float))
    return -np.asarray(lens_W.signed_distance(seg.reshape(-1, 3)), dtype=float).reshape(len(P), samples).max(axis=1)


def shaft_clearances_mm(robot: Robot, Q, p_WC, model) -> np.ndarray:
    """(K,) smallest clearance (mm, inside > 0) from `model` of the shaft points the safety
    filter watches at each posture Q (K, 6) rad (planning.instrument_points: past the
    trocar, behind the tip and port, which the standoff places); inf at a posture where
    none is that deep."""
    return _watched_clearances_mm(robot, Q, p_WC, model, shaft_only=True)


def watched_clearance_mm(robot: Robot, Q, p_WC, model) -> np.ndarray:
    """(K,) smallest clearance (mm, inside > 0) from `model` of every point the safety filter
    keeps inside the retina (tip, cutter port, the shaft points past the trocar:
    planning.instrument_points) at each posture Q (K, 6) rad, trocar p_WC (3,) mm."""
    return _watched_clearances_mm(robot, Q, p_WC, model, shaft_only=False)


def _watched_clearances_mm(robot: Robot, Q, p_WC, model, shaft_only: bool, tips: list | None = None) -> np.ndarray:
    """(K,) the smallest clearance from `model` of the watched points (only the shaft's with
    `shaft_only`) per posture; inf where there are none. `tips`, when given, receives each
    posture's tip position (W, mm) from the same kinematics."""
    Q = np.atleast_2d(np.asarray(Q, dtype=float))
    pts = []
    for ip in (instrument_points(robot, q, p_WC) for q in Q):
        pts.append(ip.P_W[[k for k, name in enumerate(ip.names) if name.startswith("shaft")]] if shaft_only else ip.P_W)
        if tips is not None:
            tips.append(ip.P_W[0])
    owner = np.repeat(np.arange(len(Q)), [len(P) for P in pts])
    out = np.full(len(Q), np.inf)
    if len(owner):
        np.minimum.at(out, owner, np.asarray(model.signed_distance(np.vstack(pts)), dtype=float))
    return out


def _cells_too_near_on_the_way(robot: Robot, traj, P_used: np.ndarray, P_cells: np.ndarray, p_WC, model,
                               limit_mm: float, margin_rad: float, lens_W=None) -> dict:
    """{index into P_cells (K, 3): reason} for the cells on whose way (from the previous
    waypoint of the timed joint trajectory, sampled every SHAFT_CHECK_DT_S) or at whose
    posture a watched shaft point comes within `limit_mm` of the model ("shaft"), or else
    a joint within `margin_rad` of its limit ("reach": the spline between cells that keep
    the margin can swing past it), or else the shaft within LENS_CLEARANCE_MM of the lens
    keep-out `lens_W` (when given; "lens"). P_used (M, 3): the targets of the trajectory's
    knots, P_cells in order among them (plan_ik_scan adds midpoints)."""
    knots = np.asarray(traj.get_segment_times())
    cell_knot = np.empty(len(P_cells), dtype=int)
    j = 0
    for k, p in enumerate(P_cells):  # the midpoints lie between the cells' rows
        while not np.array_equal(P_used[j], p):
            j += 1
        cell_knot[k] = j
    ts = np.union1d(np.arange(knots[0], knots[-1], SHAFT_CHECK_DT_S), knots)
    tips, Q = [], traj.vector_values(ts).T
    near = _watched_clearances_mm(robot, Q, p_WC, model, True, tips) < limit_mm
    lens = (lens_clearances_mm(lens_W, p_WC, np.array(tips)) < LENS_CLEARANCE_MM if lens_W is not None
            else np.zeros_like(near))
    limits = np.min(robot.joint_margin_rad(Q), axis=1) < margin_rad
    # a sample belongs to the first cell reached at or after it; the shaft's reason first
    owner = np.searchsorted(knots[cell_knot], ts - 1e-12, side="left")
    out = {int(k): "lens" for k in np.unique(owner[lens])}
    out.update({int(k): "reach" for k in np.unique(owner[limits])})
    out.update({int(k): "shaft" for k in np.unique(owner[near])})
    return out


def chord_postures(robot: Robot, p_a, p_b, p_WC, q_a, q_b, step_mm: float = CHORD_STEP_MM) -> tuple[np.ndarray, list]:
    """(tips (K, 3) mm, postures [(6,) rad]) with the tip on the straight segment p_a -> p_b
    (mm, W; ends excluded, at most `step_mm` apart, at least 3) and the shaft through the
    trocar p_WC: the closed-form branch nearest the joint-space interpolation of the ends'
    postures q_a, q_b (rad); that interpolation itself where the arm does not reach the
    line. The shaft points depend only on the tip and the trocar, not on the branch or the roll."""
    p_a, p_b, p_WC = (np.asarray(x, dtype=float) for x in (p_a, p_b, p_WC))
    q_a, q_b = np.asarray(q_a, dtype=float), np.asarray(q_b, dtype=float)
    n = max(int(np.ceil(np.linalg.norm(p_b - p_a) / step_mm)), 4)
    f = np.arange(1, n) / n
    tips = p_a + f[:, None] * (p_b - p_a)
    out = []
    for fk, p in zip(f, tips):
        q_lin = q_a + fk * (q_b - q_a)
        cands = shaft_ik(robot.arm, p, (p - p_WC) / np.linalg.norm(p - p_WC), q_lin[5])
        out.append(cands[np.argmin(np.abs(cands[:, :5] - q_lin[:5]).max(axis=1))] if len(cands) else q_lin)
    return tips, out


def _port_facing_ik(robot: Robot, p_WT, p_WC, normal_W, seed, margin_rad: float):
    """RCM IK at p_WT with the port turned to the retina, nearest the seed; when J6 would
    run out of its range (the port turns about the shaft all the way round a ring), the
    same posture with J6 a full turn back (the roll unwinds between two cells: J6 turns
    the instrument about its own axis, which moves neither the shaft nor the tip). None
    when neither lies within the joint margins, or the shaft is vertical (port_roll_rad)."""
    try:
        roll = port_roll_rad(p_WT, p_WC, normal_W)
    except ValueError:  # a vertical shaft
        return None
    for unwind in (0.0, -2 * np.pi, 2 * np.pi):
        s = np.array(seed, dtype=float)
        s[5] += unwind
        try:
            q = rcm_ik(robot, p_WT, p_WC, s, roll_rad=roll)
        except IKFailure:
            continue
        if np.min(robot.joint_margin_rad(q)) >= margin_rad:
            return q
    return None


def _branch_step(q, q_prev) -> float:
    """The largest joint change (rad) between neighbouring cells, J6's full unwinding turn
    not counted (it keeps the IK branch)."""
    d = np.abs(np.asarray(q) - q_prev)
    d[5] = abs((q[5] - q_prev[5] + np.pi) % (2 * np.pi) - np.pi)
    return float(d.max())


@dataclass(frozen=True, eq=False)
class Sweep:
    """One trocar's shaving sweep: the cells kept ((ring, azimuth index) in path order), their
    targets (K, 3) W, port rolls (K,) rad and IK postures (K, 6) rad, the timed joint
    trajectory through them and its knots' targets (plan_ik_scan adds midpoints), and the
    cells dropped on the way with their reason ("reach", "shaft" or "lens")."""

    cells: list
    targets_W: np.ndarray
    roll_rad: np.ndarray
    Q: np.ndarray
    trajectory: object  # pydrake PiecewisePolynomial, rad
    targets_used_W: np.ndarray
    dropped: dict


def plan_sweep(robot: Robot, band, p_WC, model, spec, order: list, q_start=None, lens_W=None) -> Sweep:
    """The timed sweep through the trocar p_WC (3,) mm W over the cells `order` ((ring,
    azimuth index), in path order) of `band` (planning.peripheral.Band; `spec` its
    BandSpec): RCM IK with the port's roll seeded along the
    path, cells at or on whose way (the timed spline) a joint comes within the margins, or
    only on another IK branch, dropped as "reach",
    cells at or on whose way the watched shaft nears the boundary, or the shaft the lens
    keep-out `lens_W` (W, when given; the cells' own rule, LENS_CLEARANCE_MM), dropped as
    "shaft" or "lens". IKFailure when no cell is left."""
    limit = spec.boundary_mm + SHAFT_SLACK_MM
    p_WC = np.asarray(p_WC, dtype=float)
    q = q_start
    kept, Q, dropped = [], [], {}
    for r, i in order:  # RCM IK with the port's roll, seeded along the path; a failing cell is "reach"
        t, n = band.target_W[r, i], band.normal_W[r, i]
        q = _port_facing_ik(robot, t, p_WC, n, start_posture(robot, t, p_WC) if q is None else q,
                            np.radians(spec.min_margin_deg))
        if q is None:
            dropped[(r, i)] = "reach"
            q = Q[-1] if Q else None
            continue
        jump = _branch_step(q, Q[-1]) if Q else 0.0
        if np.min(robot.joint_margin_rad(q)) < np.radians(spec.min_margin_deg) or jump > MAX_JOINT_STEP_RAD:
            dropped[(r, i)] = "reach"  # beyond the margins, or only on another branch (no continuous path)
            q = Q[-1] if Q else None
            continue
        # at the cell and on the way there from the last cell kept (a first, cheap look along
        # the straight tip segment the timed path follows, RCM held)
        tips, on_way = chord_postures(robot, band.target_W[kept[-1]], t, p_WC, Q[-1], q) if Q else (t[None], [])
        if shaft_clearances_mm(robot, [q] + on_way, p_WC, model).min() < limit:
            dropped[(r, i)] = "shaft"
        elif lens_W is not None and lens_clearances_mm(lens_W, p_WC, tips).min() < LENS_CLEARANCE_MM:
            dropped[(r, i)] = "lens"
        if (r, i) in dropped:
            q = Q[-1] if Q else None
            continue
        kept.append((r, i))
        Q.append(q)
    midpoints = {}  # the timing's midpoint IK, kept across the re-timings below (planning.scan.plan_ik_scan)
    while True:  # the timed trajectory, densely: drop the cells whose way in still nears the boundary
        if not kept:
            raise IKFailure("no cell of the band is reachable from this trocar")
        P = np.array([band.target_W[r, i] for r, i in kept])
        roll = np.array([port_roll_rad(band.target_W[r, i], p_WC, band.normal_W[r, i]) for r, i in kept])
        if len(kept) == 1:  # one cell: the tip holds it for one sweep width's time
            dwell = spec.spacing_mm / spec.tip_speed_mm_s
            return Sweep(kept, P, roll, np.array(Q), PiecewisePolynomial.FirstOrderHold([0.0, dwell], np.array([Q[0], Q[0]]).T),
                         P[[0, 0]], dropped)
        traj, P_used, _ = plan_ik_scan(robot, P, p_WC, spec.tip_speed_mm_s, roll_rad=roll, Q_waypoints=Q,
                                       midpoints=midpoints)
        bad = _cells_too_near_on_the_way(robot, traj, P_used, P, p_WC, model, limit,
                                         np.radians(spec.min_margin_deg), lens_W)
        if not bad:
            return Sweep(kept, P, roll, np.array(Q), traj, P_used, dropped)
        for k, why in bad.items():
            dropped[kept[k]] = why
        keep = np.setdiff1d(np.arange(len(kept)), list(bad))
        kept, Q = [kept[k] for k in keep], [Q[k] for k in keep]
