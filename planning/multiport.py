"""Peripheral vitrectomy of the whole band through several ports, with planned port switches.

Every band cell (planning.peripheral: equator to ora serrata, all the way round, on the
FITTED model) gets its reason from each port (planning.peripheral.cell_reasons with the
port's trocar). A cell no port reaches keeps the reason of the port that got furthest
through the checks (uncertain, lens, then port, then reach: "reach" says the geometry
allows it and only the arm does not; "uncertain" that the model's uncertainty puts the
filter's boundary across the shaving target, planning.field_model); when pushing the wall in by DEPRESSION_MM along the normal (a
scleral depressor's indentation) would let some port reach it, its reason is
"depression": it needs scleral depression, which this simulation does not model.

Assignment: ports in the given order (the scenario's trocar's port first, so the
model-building scan and the first sweep share the trocar); each port is visited once, so
a plan has (ports used - 1) switches, the fewest for that set of ports. A cell several
working ports reach goes to the one whose straight shaft keeps furthest from the retina
(the clearance varies smoothly over the band, so each port's cells form few regions and
its serpentine does not zig-zag across the other's); the infusion port, used as a
working port, takes only cells no working port reaches; a cell within a few mm of a
port, where no shaft point the filter watches is that deep and the shaft crosses the
wall right behind the cutter, goes to another port that reaches it. A port sweeps its
cells region by region; a cell a sweep drops (IK branch, the shaft or the lens on the
way) gets another pass through the same port (a re-entry) or is offered to the ports
after it. A region of fewer than MIN_PASS_CELLS cells gets no pass of its own, nor does
one left after MAX_SWEEPS_PER_PORT passes: a port reaches its cells, but unless a later
port sweeps them their reason is "declined" (the planner declined the pass), not the
geometry's. A pass enters and leaves along the shaft line of an end cell of its
serpentine, or of a door cell nearer the trocar's side when the wrist cannot take the
instrument out along the end cell's line.

A switch is withdraw (the tip back along the shaft to EXIT_MM outside the trocar, or
as far as the arm reaches but at least MIN_EXIT_MM, at INSERT_SPEED_MM_S), move (outside
the eye, the tip on an arc about it, at MOVE_SPEED_MM_S) and insert (along the next
pass's first shaft line to its first cell); every piece timed within the joints' speed
limits (planning.port_moves).

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

import dataclasses
import time
from dataclasses import dataclass

import numpy as np
from pydrake.trajectories import PiecewisePolynomial

from planning.field_model import retina_of
from planning.ik import IKFailure
from planning.peripheral import (Band, BandSpec, Sweep, band_surface, cell_reach, cell_reasons, plan_sweep, port_roll_rad,
                                 serpentine)
from planning.port_moves import (EXIT_MM, INSERT_SPEED_MM_S, MIN_EXIT_MM, PortSwitch, line_trajectory,  # noqa: F401
                                 port_switches)
from planning.robot import Robot
from planning.sweep import SHAFT_SLACK_MM, watched_clearance_mm

DEFAULT_PORTS = ("superonasal", "superotemporal")  # the two working ports of planning.ports' layout
CHECK_ORDER = ("uncertain", "lens", "port", "reach", "shaft")  # how far a cell got through a port's checks
UNREACHABLE = ("uncertain", "lens", "port", "reach", "shaft", "depression", "declined")
DEPRESSION_MM = 2.0  # indentation of the wall by a scleral depressor (a few mm in practice)
SHALLOW_RANK = -1e9  # plan_ports' rank of a cell next to the port (below any clearance, above not reaching it)
MAX_SWEEPS_PER_PORT = 8  # passes through one port (each after the first is a re-entry)
MAX_DOOR_TRIES = 30  # cells tried as a pass's door (the arm takes the instrument out along its shaft line)
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


def _segment(robot: Robot, band: Band, port, p_WC, model, spec: BandSpec, mask: np.ndarray, lens_W) -> PortSegment | None:
    """The port's sweep over the cells of `mask` with its insertion and withdrawal; None
    when none of them can be swept, or the arm cannot insert or withdraw the instrument
    along a shaft line into or out of the sweep within its joint limits. The sweep enters
    (leaves) at its first (last) cell, or, where the arm cannot take the instrument EXIT_MM
    out of the trocar along that cell's shaft line (the wrist at its limit at a far, deep
    cell), at the nearest of its cells where it can (a door cell, visited twice); with no
    such door, at the end cell when the arm takes the tip at least MIN_EXIT_MM out, else at
    the nearest door where it does."""
    best = None
    for flip in (False, True):  # the serpentine's two pairs of end cells
        try:
            sweep = plan_sweep(robot, band, p_WC, model, spec, serpentine(band, mask, flip), lens_W=lens_W)
        except IKFailure:
            return None
        lines = _end_lines(robot, band, sweep, p_WC, EXIT_MM)
        if None in lines:
            sweep, lines = _through_doors(robot, band, sweep, lines, p_WC, model, spec, lens_W)
        if None not in lines:
            best = sweep, lines
            break
        if best is None:  # the ends themselves, or doors, where the arm takes the tip out at least MIN_EXIT_MM
            short = _end_lines(robot, band, sweep, p_WC, MIN_EXIT_MM)
            if None in short:
                sweep, short = _through_doors(robot, band, sweep, short, p_WC, model, spec, lens_W, MIN_EXIT_MM)
            best = (sweep, short) if None not in short else None
    if best is None:
        return None
    sweep, (insert, withdraw_reversed) = best
    limit = spec.boundary_mm + SHAFT_SLACK_MM
    withdraw = _reversed(withdraw_reversed)
    return PortSegment(port, np.asarray(p_WC, dtype=float), sweep, insert, withdraw,
                       inside_from_s(robot, insert, p_WC, model, limit),
                       withdraw.end_time() - inside_from_s(robot, withdraw_reversed, p_WC, model, limit))


def _end_line(robot: Robot, band: Band, cell, q, p_WC, out_mm: float):
    """The insertion along the shaft line to `cell` (ring, azimuth index) ending at its
    posture q (rad), from EXIT_MM outside the trocar (line_trajectory), or None when the
    arm cannot take the tip `out_mm` out of the trocar along it."""
    t = band.target_W[cell]
    depth = float(np.linalg.norm(t - p_WC))
    try:
        return line_trajectory(robot, q, t, p_WC, port_roll_rad(t, p_WC, band.normal_W[cell]), depth + EXIT_MM,
                               INSERT_SPEED_MM_S, depth + out_mm)[0]
    except IKFailure:
        return None


def _end_lines(robot: Robot, band: Band, sweep: Sweep, p_WC, out_mm: float) -> tuple:
    """(insertion to the sweep's first cell, the withdrawal from its last one run backwards),
    each None where the arm cannot take the tip `out_mm` out of the trocar along that shaft line."""
    return tuple(_end_line(robot, band, sweep.cells[k], sweep.Q[k], p_WC, out_mm) for k in (0, -1))


def _through_doors(robot: Robot, band: Band, sweep: Sweep, lines: tuple, p_WC, model, spec: BandSpec, lens_W,
                   out_mm: float = EXIT_MM) -> tuple:
    """(sweep, its end lines) with each end whose line fails moved to a door cell: of the
    sweep's cells (the nearest to that end first, at most MAX_DOOR_TRIES), the first whose
    shaft line the arm can take `out_mm` out; the sweep re-planned with the door before its
    first cell or after its last one (its way there checked as any other). The given sweep
    and lines when no door works."""
    doors = []
    for k, line in zip((0, -1), lines):
        if line is not None:
            doors.append([])
            continue
        near = np.argsort(np.linalg.norm(sweep.targets_W - sweep.targets_W[k], axis=1))[1:MAX_DOOR_TRIES + 1]
        door = next((j for j in near if _end_line(robot, band, sweep.cells[j], sweep.Q[j], p_WC, out_mm) is not None), None)
        if door is None:
            return sweep, lines
        doors.append([sweep.cells[door]])
    order = doors[0] + list(sweep.cells) + doors[1]
    try:
        again = plan_sweep(robot, band, p_WC, model, spec, order, lens_W=lens_W)
    except IKFailure:
        return sweep, lines
    if again.cells[0] != order[0] or again.cells[-1] != order[-1]:  # a door's way in was refused
        return sweep, lines
    again = dataclasses.replace(again, dropped={**sweep.dropped, **again.dropped})
    return again, _end_lines(robot, band, again, p_WC, out_mm)


def inside_from_s(robot: Robot, line: PiecewisePolynomial, p_WC, model, limit_mm: float) -> float:
    """The time (s) on an insertion `line` (outside the eye -> its last posture) from which
    every watched point (watched_clearance_mm) stays at least min(`limit_mm`, its depth at
    the line's last posture) inside `model`, sampled every DEPTH_CHECK_DT_S."""
    ts = np.linspace(0.0, line.end_time(), int(np.ceil(line.end_time() / DEPTH_CHECK_DT_S)) + 1)  # no sliver at the end
    c = watched_clearance_mm(robot, line.vector_values(ts).T, p_WC, model)
    shallow = np.flatnonzero(c < min(limit_mm, c[-1]) - 1e-9)
    return float(ts[shallow[-1] + 1]) if len(shallow) else 0.0


def _reversed(traj: PiecewisePolynomial) -> PiecewisePolynomial:
    """The cubic trajectory `traj` run backwards, from time 0: the same curve (a cubic
    segment is its ends' values and velocities), the velocities negated."""
    t = np.asarray(traj.get_segment_times())
    Q, V = traj.vector_values(t), traj.derivative(1).vector_values(t)
    return PiecewisePolynomial.CubicHermite(t[-1] - t[::-1], Q[:, ::-1], -V[:, ::-1])


def plan_ports(robot: Robot, scenario, model, ports, spec: BandSpec = BandSpec(), surface=None) -> MultiPortPlan:
    """Plan the band of `model` through `ports` (planning.ports.Port, in visiting order;
    each named in scenario.ports); `surface`: the band's planning.peripheral.band_surface
    of `model` when the caller has it (else computed here). ValueError for a bad band or
    an unknown port, IKFailure when no port sweeps any cell."""
    t0 = time.perf_counter()
    ports = tuple(ports)
    trocars = [scenario.p_WC_of(p.name) for p in ports]  # ValueError for an unknown port
    az, z, S, N = band_surface(model, scenario.eye_pose, spec) if surface is None else surface
    shape = S.shape[:2]
    T = S + spec.standoff_mm * N
    Tf, Nf = T.reshape(-1, 3), N.reshape(-1, 3)
    by_port = cell_reasons_by_port(robot, scenario, Tf, Nf, spec, ports, model)
    reason = combined_reason([by_port[p.name][0] for p in ports])
    static_miss = (reason != "ok").reshape(shape)
    # the first port to take a cell: of those that reach it, the one whose shaft keeps furthest from the retina
    # (the infusion port, when used as a working port, takes only what the working ports cannot). A cell within
    # a few mm of a port (no watched shaft point that deep: clearance +inf) ranks below every other port that
    # reaches it: there the shaft crosses the wall right behind the cutter, which turns fast about the trocar.
    clear = np.array([np.where(by_port[p.name][0] != "ok", -np.inf, np.where(np.isposinf(by_port[p.name][2]),
                                                                             SHALLOW_RANK, by_port[p.name][2]))
                      for p in ports])
    working = np.array([p.role == "working" for p in ports])
    first = np.where((clear[working] > -np.inf).any(axis=0)[None] & ~working[:, None], -np.inf, clear)
    choice = np.where(first.max(axis=0) > -np.inf, np.argmax(first, axis=0), -1)
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
            seg = _segment(robot, band, port, p_WC, model, spec, part, scenario.lens_W)
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
            for m in queue:
                if m.sum() < MIN_PASS_CELLS:
                    band.reason[m & (port_of < 0)] = "declined"
            queue = [m for m in queue if m.sum() >= MIN_PASS_CELLS]
            segments.append(seg)
        for m in queue:  # left after MAX_SWEEPS_PER_PORT passes
            band.reason[m & (port_of < 0)] = "declined"
        open_cells = (open_cells | mask) & (port_of < 0)
    band.reason[port_of >= 0] = "ok"
    band.reason[(port_of < 0) & (band.reason == "ok")] = "shaft"  # reached, but every sweep dropped it
    _mark_depression(robot, scenario, band, spec, ports, static_miss)
    switches, moves = port_switches(robot, retina_of(model), segments, scenario.eye_pose.p_WE)
    if not segments:
        counts = {r: int(np.sum(band.reason == r)) for r in UNREACHABLE if np.any(band.reason == r)}
        raise IKFailure(f"no cell of the band can be swept from these ports ({band.reason.size} cells: "
                        + ", ".join(f"{n} {r}" for r, n in counts.items()) + ")")
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
