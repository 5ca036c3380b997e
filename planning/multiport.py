"""Peripheral vitrectomy of the whole band through several ports, with planned port switches.

Every band cell (planning.peripheral: equator to ora serrata, all the way round, on the
FITTED model) gets its reason from each port (planning.peripheral.cell_reasons with the
port's trocar). A cell no port reaches keeps the reason of the port that got furthest
through the checks (lens, then port, then reach: "reach" says the geometry allows it and
only the arm does not); when pushing the wall in by DEPRESSION_MM along the normal (a
scleral depressor's indentation) would let some port reach it, its reason is
"depression": it needs scleral depression, which this simulation does not model.

Assignment: ports in the given order (the scenario's trocar's port first, so the
model-building scan and the first sweep share the trocar); each port is visited once, so
a plan has (ports used - 1) switches, the fewest for that set of ports. A cell several
working ports reach goes to the one whose straight shaft keeps furthest from the retina
(the clearance varies smoothly over the band, so each port's cells form few regions and
its serpentine does not zig-zag across the other's); the infusion port, used as a
working port, takes only cells no working port reaches. A port sweeps its cells region
by region; a cell a sweep drops (IK branch, the shaft on the way) gets another pass
through the same port (a re-entry) or is offered to the ports after it.

A switch is withdraw (the tip back along the shaft to EXIT_MM outside the trocar, or
as far as the arm reaches but at least MIN_EXIT_MM, at INSERT_SPEED_MM_S), move (outside
the eye, the tip on an arc about it, at MOVE_SPEED_MM_S) and insert (along the next
pass's first shaft line to its first cell); every piece timed within the joints' speed
limits (planning.scan.joint_trajectory).

Phases of a pass (PortSegment.pieces, in execution order): "enter" (the insertion while
the tip crosses the wall at the trocar: some point the filter watches, tip, cutter port or
shaft, lies less than the boundary + SHAFT_SLACK_MM inside the model), "insert" (the rest
of the insertion, every watched point that deep, to the first cell), "sweep", "withdraw"
(back along the shaft while every watched point is still that deep) and "exit" (through
the wall to outside the eye); "move" between passes. The depth is capped at the watched
points' own at the sweep's first (last) posture, so that "insert" ("withdraw") always
reaches the sweep. "insert", "sweep" and "withdraw" (IN_EYE_PHASES) have the instrument
inside the eye, clear of the filter's boundary: the closed loop executes them with the
filter on; "enter", "exit" and "move" pass through or outside the eye wall, where no
retina lies (the pars plana) and the filter's boundary cannot hold. Units: mm, s, rad;
frame W unless `_E`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from pydrake.trajectories import PiecewisePolynomial

from planning.ik import IKFailure, rcm_ik
from planning.peripheral import (Band, BandSpec, Sweep, band_surface, cell_reach, cell_reasons, plan_sweep, port_roll_rad,
                                 serpentine)
from planning.robot import Robot
from planning.scan import joint_trajectory
from planning.sweep import SHAFT_SLACK_MM, watched_clearance_mm

DEFAULT_PORTS = ("superonasal", "superotemporal")  # the two working ports of planning.ports' layout
CHECK_ORDER = ("lens", "port", "reach", "shaft")  # how far a cell got through a port's checks
UNREACHABLE = ("lens", "port", "reach", "shaft", "depression")
DEPRESSION_MM = 2.0  # indentation of the wall by a scleral depressor (a few mm in practice)
EXIT_MM = 10.0  # the tip's distance outside the trocar while the instrument moves between ports
MIN_EXIT_MM = 2.0  # the least the tip must clear the trocar by before the instrument moves
INSERT_SPEED_MM_S = 5.0  # tip speed along the shaft while inserting and withdrawing
LINE_STEP_MM = 1.0  # spacing of the insertion line's IK waypoints
MOVE_SPEED_MM_S = 20.0  # the tip's speed on the move outside the eye
MOVE_CLEARANCE_MM = 5.0  # the tip's arc between ports lies this much further out than its ends
MAX_SWEEPS_PER_PORT = 8  # passes through one port (each after the first is a re-entry)
MIN_PASS_CELLS = 3  # a re-entry (withdraw, insert: ~10 s) for fewer cells is not worth it
IN_EYE_PHASES = ("insert", "sweep", "withdraw")  # a pass's phases with the instrument clear inside the eye
DEPTH_CHECK_DT_S = 0.01  # the insertion's depth check: the tip moves 0.05 mm between samples at 5 mm/s


@dataclass(frozen=True, eq=False)
class PortSegment:
    """One port's work: the port (planning.ports.Port), its trocar p_WC (mm, W), the sweep
    (planning.peripheral.Sweep) and the insertion to its first cell and withdrawal from its
    last (joint trajectories, rad, each starting at time 0); `insert_inside_s`: the time on
    the insertion from which the instrument is clear inside the eye, `withdraw_inside_s`
    the time on the withdrawal up to which it is (the module's phases)."""

    port: object
    p_WC: np.ndarray
    sweep: Sweep
    insert: PiecewisePolynomial
    withdraw: PiecewisePolynomial
    insert_inside_s: float = 0.0
    withdraw_inside_s: float = 0.0

    def pieces(self) -> list[tuple[str, PiecewisePolynomial, float, float]]:
        """[(phase, joint trajectory, t0 s, t1 s)]: enter, insert, sweep, withdraw, exit, each
        the trajectory's window [t0, t1]."""
        sweep = self.sweep.trajectory
        return [("enter", self.insert, 0.0, self.insert_inside_s),
                ("insert", self.insert, self.insert_inside_s, self.insert.end_time()),
                ("sweep", sweep, sweep.start_time(), sweep.end_time()),
                ("withdraw", self.withdraw, 0.0, self.withdraw_inside_s),
                ("exit", self.withdraw, self.withdraw_inside_s, self.withdraw.end_time())]


@dataclass(frozen=True)
class PortSwitch:
    """A planned switch between ports: durations (s) of its withdraw, move and insert, and the
    tip's smallest distance outside the model's retina during the move (mm, > 0 outside)."""

    from_port: str
    to_port: str
    withdraw_s: float
    move_s: float
    insert_s: float
    move_min_outside_mm: float

    @property
    def duration_s(self) -> float:
        return self.withdraw_s + self.move_s + self.insert_s


@dataclass(frozen=True, eq=False)
class MultiPortPlan:
    """The band (its `reason`: "ok" for a cell some port's sweep visits, else its reason),
    `port_of` (n_rings, n_az) the index into `ports` of the port that sweeps each cell (-1:
    none), `reasons_by_port` each port's own reasons, the segments (in execution order),
    the switches between them, the moves (joint trajectories, between segments) and the
    planning time (s)."""

    band: Band
    ports: tuple
    port_of: np.ndarray
    reasons_by_port: dict
    segments: list
    switches: list
    moves: list
    plan_time_s: float


def regions(mask: np.ndarray) -> list[np.ndarray]:
    """The connected regions of `mask` (n_rings, n_az) bool (cells touching across an edge
    or a corner, azimuth wrapping round), largest first: one sweep each, so no sweep
    crosses cells it leaves out."""
    from scipy.ndimage import label

    lab, n = label(mask, structure=np.ones((3, 3), dtype=int))
    parent = list(range(n + 1))

    def root(x):
        while parent[x] != x:
            x = parent[x]
        return x

    rings = mask.shape[0]
    for r in range(rings):  # the seam: the last azimuth touches the first
        for dr in (-1, 0, 1):
            if 0 <= r + dr < rings and lab[r, -1] and lab[r + dr, 0]:
                parent[root(lab[r, -1])] = root(lab[r + dr, 0])
    roots = np.array([root(x) for x in range(n + 1)])
    out = [np.isin(lab, np.flatnonzero(roots == g)) & mask for g in sorted(set(roots[1:].tolist()))]
    return sorted(out, key=lambda m: -int(m.sum()))


def cell_reasons_by_port(robot: Robot, scenario, T: np.ndarray, N: np.ndarray, spec: BandSpec, ports, model) -> dict:
    """{port name: (reasons (M,), port angle deg (M,), shaft clearance mm (M,))} for targets T
    (M, 3) W with normals N (planning.peripheral.cell_reach against `model`)."""
    return {p.name: cell_reach(robot, scenario, T, N, spec, scenario.p_EC_of(p.name), model) for p in ports}


def combined_reason(reasons: list) -> np.ndarray:
    """(M,) "ok" where some port's reason is "ok", else the furthest reason in CHECK_ORDER."""
    R = np.array(reasons, dtype=object)
    rank = np.vectorize(lambda r: len(CHECK_ORDER) if r == "ok" else CHECK_ORDER.index(r))(R)
    best = rank.max(axis=0)
    return np.array(["ok" if b == len(CHECK_ORDER) else CHECK_ORDER[b] for b in best], dtype=object)


def line_trajectory(robot: Robot, q_end, p_WT, p_WC, roll_rad: float, length_mm: float, speed_mm_s: float,
                    min_length_mm: float):
    """(joint trajectory rad, its length mm) of the tip moving along the shaft line trocar
    p_WC -> p_WT to p_WT from up to `length_mm` behind it (outside the eye when longer
    than |p_WT - p_WC|), ending at q_end; timed at `speed_mm_s` (planning.scan.joint_trajectory)
    with the roll held. The line starts where the arm still reaches it (IK every
    LINE_STEP_MM); IKFailure when that is less than `min_length_mm`."""
    p_T, p_C = np.asarray(p_WT, dtype=float), np.asarray(p_WC, dtype=float)
    u = (p_T - p_C) / np.linalg.norm(p_T - p_C)
    pivot = p_T - (length_mm + 20.0) * u  # the same line, its pivot behind every point of the move
    s = np.linspace(0.0, length_mm, max(int(np.ceil(length_mm / LINE_STEP_MM)), 1) + 1)
    Q = [np.asarray(q_end, dtype=float)]
    for d in s[1:]:
        try:
            Q.append(rcm_ik(robot, p_T - d * u, pivot, Q[-1], roll_rad=roll_rad))
        except IKFailure:
            break
    reached = s[len(Q) - 1]
    if reached < min_length_mm:
        raise IKFailure(f"the instrument cannot leave the trocar along its shaft from p_WT_mm = {np.round(p_T, 3)}: "
                        f"the arm reaches {reached:.1f} mm of the {min_length_mm:.1f} mm needed")
    Q = np.array(Q[::-1])
    return joint_trajectory(robot, Q, p_T - s[:len(Q)][::-1, None] * u, speed_mm_s), float(reached)


def joint_move(robot: Robot, q0, q1, p_WE, clearance_mm: float) -> PiecewisePolynomial:
    """The move outside the eye between two postures q0, q1 (rad) whose tips are outside
    it: the tip on an arc about the eye centre p_WE (mm, W) bulging `clearance_mm` further
    out than the line between the tips' own distances, the shaft direction turning evenly between its two
    (closed-form IK, the branch nearest the last sample), timed at MOVE_SPEED_MM_S within
    the joints' speed limits (planning.scan.joint_trajectory); a direct joint-space move
    when the arc leaves the arm's reach."""
    from planning.closed_form import shaft_ik

    q0, q1 = np.asarray(q0, dtype=float), np.asarray(q1, dtype=float)
    R0, t0 = robot.pose("I", q0)[0], robot.pose("T", q0)[1]
    R1, t1 = robot.pose("I", q1)[0], robot.pose("T", q1)[1]
    d0, d1 = t0 - p_WE, t1 - p_WE
    r0, r1 = np.linalg.norm(d0), np.linalg.norm(d1)
    Q = [q0]
    for s in np.linspace(0.0, 1.0, 13)[1:-1]:
        d = (1 - s) * d0 / r0 + s * d1 / r1
        u = (1 - s) * R0[:, 0] + s * R1[:, 0]
        r = (1 - s) * r0 + s * r1 + clearance_mm * np.sin(np.pi * s)
        cands = shaft_ik(robot.arm, p_WE + r * d / np.linalg.norm(d), u / np.linalg.norm(u), q0[5] + s * (q1[5] - q0[5]))
        ok = [c for c in cands if np.all(robot.joint_margin_rad(c) >= 0)]
        if not ok:
            Q = [q0]
            break
        Q.append(min(ok, key=lambda c: np.abs(c - Q[-1]).max()))
    Q = np.array(Q + [q1])
    return joint_trajectory(robot, Q, np.array([robot.pose("T", q)[1] for q in Q]), MOVE_SPEED_MM_S)


def _segment(robot: Robot, band: Band, port, p_WC, model, spec: BandSpec, mask: np.ndarray) -> PortSegment | None:
    """The port's sweep over the cells of `mask` with its insertion and withdrawal; None
    when none of them can be swept, or the arm cannot insert or withdraw the instrument
    along the first or last cell's shaft line within its joint limits."""
    try:
        sweep = plan_sweep(robot, band, p_WC, model, spec, serpentine(band, mask))
    except IKFailure:
        return None
    lines = []
    for k in (0, -1):
        (r, i), q = sweep.cells[k], sweep.Q[k]
        t = band.target_W[r, i]
        depth = float(np.linalg.norm(t - p_WC))
        try:
            lines.append(line_trajectory(robot, q, t, p_WC, port_roll_rad(t, p_WC, band.normal_W[r, i]), depth + EXIT_MM,
                                         INSERT_SPEED_MM_S, depth + MIN_EXIT_MM)[0])
        except IKFailure:
            return None
    insert, withdraw_reversed = lines
    limit = spec.boundary_mm + SHAFT_SLACK_MM
    withdraw = _reversed(withdraw_reversed)
    return PortSegment(port, np.asarray(p_WC, dtype=float), sweep, insert, withdraw,
                       inside_from_s(robot, insert, p_WC, model, limit),
                       withdraw.end_time() - inside_from_s(robot, withdraw_reversed, p_WC, model, limit))


def inside_from_s(robot: Robot, line: PiecewisePolynomial, p_WC, model, limit_mm: float) -> float:
    """The time (s) on an insertion `line` (outside the eye -> its last posture) from which
    every watched point (watched_clearance_mm) stays at least min(`limit_mm`, its depth at
    the line's last posture) inside `model`, sampled every DEPTH_CHECK_DT_S."""
    ts = np.linspace(0.0, line.end_time(), int(np.ceil(line.end_time() / DEPTH_CHECK_DT_S)) + 1)  # no sliver at the end
    c = watched_clearance_mm(robot, line.vector_values(ts).T, p_WC, model)
    shallow = np.flatnonzero(c < min(limit_mm, c[-1]) - 1e-9)
    return float(ts[shallow[-1] + 1]) if len(shallow) else 0.0


def _reversed(traj: PiecewisePolynomial) -> PiecewisePolynomial:
    """The trajectory run backwards, from time 0."""
    t = np.asarray(traj.get_segment_times())
    Q = np.array([traj.value(x)[:, 0] for x in t])
    return PiecewisePolynomial.CubicShapePreserving(t[-1] - t[::-1], Q[::-1].T, zero_end_point_derivatives=True)


def plan_ports(robot: Robot, scenario, model, ports, spec: BandSpec = BandSpec()) -> MultiPortPlan:
    """Plan the band of `model` through `ports` (planning.ports.Port, in visiting order;
    each named in scenario.ports). ValueError for a bad band or an unknown port,
    IKFailure when no port sweeps any cell."""
    t0 = time.perf_counter()
    ports = tuple(ports)
    trocars = [scenario.p_WC_of(p.name) for p in ports]  # ValueError for an unknown port
    az, z, S, N = band_surface(model, scenario.eye_pose, spec)
    shape = S.shape[:2]
    T = S + spec.standoff_mm * N
    Tf, Nf = T.reshape(-1, 3), N.reshape(-1, 3)
    by_port = cell_reasons_by_port(robot, scenario, Tf, Nf, spec, ports, model)
    reason = combined_reason([by_port[p.name][0] for p in ports])
    static_miss = (reason != "ok").reshape(shape)
    # the first port to take a cell: of those that reach it, the one whose shaft keeps furthest from the retina
    # (the infusion port, when used as a working port, takes only what the working ports cannot)
    clear = np.array([np.where(by_port[p.name][0] == "ok", by_port[p.name][2], -np.inf) for p in ports])
    working = np.array([p.role == "working" for p in ports])
    first = np.where(np.isfinite(clear[working]).any(axis=0)[None] & ~working[:, None], -np.inf, clear)
    choice = np.where(np.isfinite(first.max(axis=0)), np.argmax(first, axis=0), -1)
    band = Band(az, z, S, N, T, reason.reshape(shape).copy(), np.full(shape, np.nan))
    port_of = np.full(shape, -1)
    open_cells = np.zeros(shape, dtype=bool)  # dropped by an earlier port's sweep, still to be offered
    segments = []
    for k, (port, p_WC) in enumerate(zip(ports, trocars)):
        ok_k = (by_port[port.name][0] == "ok").reshape(shape)
        mask = ((choice.reshape(shape) == k) | open_cells) & ok_k
        if not mask.any():
            continue
        queue, rounds = regions(mask), 0
        while queue and rounds < MAX_SWEEPS_PER_PORT:
            part = queue.pop(0)
            rounds += 1
            seg = _segment(robot, band, port, p_WC, model, spec, part)
            if seg is None:  # the arm cannot sweep this region from here: "reach" unless another port sweeps it
                band.reason[part & (band.reason == "ok")] = "reach"
                continue
            for (r, i) in seg.sweep.cells:
                port_of[r, i] = k
                band.port_deg[r, i] = by_port[port.name][1].reshape(shape)[r, i]
            left = np.zeros(shape, dtype=bool)
            for cell, why in seg.sweep.dropped.items():
                band.reason[cell] = why
                left[cell] = True
            # a sweep drops the cells it cannot join on its path (an IK branch, the shaft on the
            # way); from a fresh entry they may be swept: another pass (a re-entry)
            queue = sorted(queue + regions(left), key=lambda m: -int(m.sum()))
            queue = [m for m in queue if m.sum() >= MIN_PASS_CELLS]
            segments.append(seg)
        open_cells = (open_cells | mask) & (port_of < 0)
    band.reason[port_of >= 0] = "ok"
    band.reason[(port_of < 0) & (band.reason == "ok")] = "shaft"  # reached, but every sweep dropped it
    _mark_depression(robot, scenario, band, spec, ports, static_miss)
    switches, moves = _switches(robot, model, segments, scenario.eye_pose.p_WE)
    if not segments:
        raise IKFailure("no cell of the band can be swept from these ports")
    return MultiPortPlan(band, ports, port_of, {n: r[0].reshape(shape) for n, r in by_port.items()}, segments,
                         switches, moves, time.perf_counter() - t0)


def _mark_depression(robot: Robot, scenario, band: Band, spec: BandSpec, ports, static_miss: np.ndarray) -> None:
    """Cells no port reaches (`static_miss`) for the lens, the port angle or the arm's reach
    whose target, with the wall pushed DEPRESSION_MM in, some port reaches: their reason
    becomes "depression"."""
    miss = static_miss & np.isin(band.reason, ("lens", "port", "reach"))
    if not miss.any():
        return
    T = band.target_W[miss] + DEPRESSION_MM * band.normal_W[miss]
    found = np.zeros(len(T), dtype=bool)
    for p in ports:
        found |= cell_reasons(robot, scenario, T, band.normal_W[miss], spec, p_EC=scenario.p_EC_of(p.name))[0] == "ok"
    idx = np.argwhere(miss)[found]
    band.reason[tuple(idx.T)] = "depression"


def _switches(robot: Robot, model, segments: list, p_WE) -> tuple[list, list]:
    """The switches between consecutive segments and their moves outside the eye."""
    switches, moves = [], []
    for a, b in zip(segments[:-1], segments[1:]):
        q0, q1 = a.withdraw.value(a.withdraw.end_time())[:, 0], b.insert.value(0.0)[:, 0]
        move = joint_move(robot, q0, q1, p_WE, MOVE_CLEARANCE_MM)
        ts = np.linspace(0.0, move.end_time(), 50)
        tips = np.array([robot.pose("T", move.value(t)[:, 0])[1] for t in ts])
        outside = float(-np.max(np.asarray(model.signed_distance(tips), dtype=float)))
        switches.append(PortSwitch(a.port.name, b.port.name, a.withdraw.end_time(), move.end_time(), b.insert.end_time(),
                                   outside))
        moves.append(move)
    return switches, moves
