"""A multi-port plan (planning.multiport) executed through the closed loop, pass by pass.

Each pass (PortSegment) runs as one closed-loop segment on its own trocar (the filter's
RCM and monitored points on it: ClosedLoop.run_segments): its in-eye phases
(planning.multiport.IN_EYE_PHASES: the insertion from where the instrument is clear
inside the eye, the sweep, the withdrawal back to there) as one tip-path command, the
tip positions and the shaft's spin sampled from the planned joint trajectories. The
phases through and outside the eye wall ("enter", "exit", "move") are not simulated: the
next pass starts at its planned in-eye posture. `phase_figures` cuts the run into the
passes' phases and reports each one's executed time, filter interventions, true
clearance, RCM error and where the tip ended against the plan. Units: mm, s, rad; frame W.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from eval.experiments.command_sources import TipPathCommand
from planning.multiport import IN_EYE_PHASES

SAMPLE_S = 0.02  # the command's tip samples: 0.1 mm apart at 5 mm/s, 0.4 mm at the joints' fastest


@dataclass(frozen=True, eq=False)
class ExecutedPass:
    """One pass as the closed loop runs it: `port` (name), trocar `p_WC` (3,) mm, the tip-path
    `command`, start posture `q0` (6,) rad, `phases` ((phase, t0 s, t1 s), ...) from the
    pass's start (in-eye phases with a duration only), the planned samples `times_s` (K,),
    `Q` (K, 6) rad, `tips_W` (K, 3) mm and their `phase` (K,) names, `depth_mm` the tip's
    depth past the trocar along the shaft at the loop's start and end."""

    port: str
    p_WC: np.ndarray
    command: TipPathCommand
    q0: np.ndarray
    phases: tuple
    times_s: np.ndarray
    Q: np.ndarray
    tips_W: np.ndarray
    phase: np.ndarray
    depth_mm: tuple

    @property
    def duration_s(self) -> float:
        return float(self.phases[-1][2])

    def segment(self) -> tuple:
        """(p_WC, source, q0, duration_s): ClosedLoop.run_segments' segment."""
        return self.p_WC, self.command, self.q0, self.duration_s


def shaft_spin_rad(robot, traj, ts: np.ndarray) -> np.ndarray:
    """(K,) the instrument's turn about its own shaft along the joint trajectory at times
    ts (s) from the first: the integral of its angular velocity along the shaft, which is
    what the filter's roll command (rad/s about the shaft) asks for."""
    Q, dQ = traj.vector_values(ts).T, traj.derivative(1).vector_values(ts).T
    rate = np.array([robot.pose("I", q)[0][:, 0] @ (robot.spatial_jacobian("I", q)[:3] @ dq) for q, dq in zip(Q, dQ)])
    return np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(ts))])


def executed_pass(robot, seg) -> ExecutedPass:
    """The closed loop's pass for a planning.multiport.PortSegment."""
    times, Q, tips, roll, names, phases = [], [], [], [], [], []
    t_pass, spin = 0.0, 0.0
    for phase, traj, a, b in seg.pieces():
        if phase not in IN_EYE_PHASES or b - a <= 1e-9:
            continue
        ts = np.append(np.arange(a, b, SAMPLE_S), b)
        if len(ts) > 2 and b - ts[-2] < 1e-3:  # no sliver at the end
            ts = np.delete(ts, -2)
        Qp = traj.vector_values(ts).T
        turn = spin + shaft_spin_rad(robot, traj, ts)
        skip = 1 if times else 0  # a phase starts where the last ended
        times.append(t_pass + ts[skip:] - a)
        Q.append(Qp[skip:])
        tips.append(np.array([robot.pose("T", q)[1] for q in Qp[skip:]]))
        roll.append(turn[skip:])
        names += [phase] * (len(ts) - skip)
        phases.append((phase, t_pass, t_pass + (b - a)))
        t_pass, spin = t_pass + (b - a), float(turn[-1])
    times, Q, tips, roll = np.concatenate(times), np.vstack(Q), np.vstack(tips), np.concatenate(roll)
    u = [robot.pose("I", q)[0][:, 0] for q in (Q[0], Q[-1])]
    depth = tuple(float(v @ (p - seg.p_WC)) for v, p in zip(u, (tips[0], tips[-1])))
    return ExecutedPass(seg.port.name, np.asarray(seg.p_WC, dtype=float), TipPathCommand(times, tips, roll_rad=roll),
                        Q[0], tuple(phases), times, Q, tips, np.array(names, dtype=object), depth)


def executed_passes(robot, plan) -> list[ExecutedPass]:
    """Every pass of the plan (planning.multiport.MultiPortPlan) in execution order."""
    return [executed_pass(robot, seg) for seg in plan.segments]


def step_phases(run, passes: list[ExecutedPass]) -> tuple[np.ndarray, np.ndarray]:
    """(pass index (M,), phase name (M,)) of each step of `run` (eval.closed_loop.LoopRun of
    run_segments over the passes' segments, in order): the step at time t belongs to the
    phase whose window [t0, t1) holds t."""
    starts, owner, names = [], [], []
    t0 = 0.0
    for k, p in enumerate(passes):
        for name, a, _ in p.phases:
            starts.append(t0 + a)
            owner.append(k)
            names.append(name)
        t0 += p.duration_s
    idx = np.clip(np.searchsorted(np.array(starts), run.t + 1e-9, side="right") - 1, 0, len(starts) - 1)
    return np.array(owner)[idx], np.array(names, dtype=object)[idx]


def phase_figures(robot, run, passes: list[ExecutedPass], d_safe_mm: float) -> dict:
    """{"phases": {phase: figures over every pass}, "passes": [per pass: port, depth at the
    loop's start and end, {phase: figures}]}. Figures: `planned_s`, `executed_s` (the
    control steps in the phase x the period), `filter_intervention_fraction`,
    `min_true_clearance_mm`, `violations` (steps below d_safe_mm - 0.05 mm),
    `failsafe_steps`, `max_rcm_error_um` (about the pass's trocar) and `max_end_error_mm`
    (the tip at the phase's last step from the planned point at its end)."""
    dt = float(run.t[1] - run.t[0])
    owner, name = step_phases(run, passes)

    def figures(mask, planned_s, ends):
        return {"planned_s": float(planned_s), "executed_s": float(mask.sum() * dt),
                "filter_intervention_fraction": float(run.intervened[mask].mean()) if mask.any() else None,
                "min_true_clearance_mm": float(run.true_clearance_mm[mask].min()) if mask.any() else None,
                "violations": int(np.sum(run.true_clearance_mm[mask] < d_safe_mm - 0.05)),
                "failsafe_steps": int(np.sum(~run.ok[mask])),
                "max_rcm_error_um": float(1e3 * np.nanmax(run.rcm_error_mm[mask])) if mask.any() else None,
                "max_end_error_mm": max(ends) if ends else None}

    def end_error(mask, target):
        last = np.flatnonzero(mask)
        return float(np.linalg.norm(robot.pose("T", run.q[last[-1]])[1] - target)) if len(last) else None

    per_pass = []
    for k, p in enumerate(passes):
        figs = {}
        for ph, a, b in p.phases:
            m = (owner == k) & (name == ph)
            e = end_error(m, p.tips_W[np.flatnonzero(p.phase == ph)[-1]])
            figs[ph] = figures(m, b - a, [e] if e is not None else [])
        per_pass.append({"port": p.port, "loop_start_depth_mm": p.depth_mm[0], "loop_end_depth_mm": p.depth_mm[1],
                         "phases": figs})
    totals = {}
    for ph in IN_EYE_PHASES:
        m = name == ph
        ends = [f["phases"][ph]["max_end_error_mm"] for f in per_pass if ph in f["phases"]]
        totals[ph] = figures(m, sum(b - a for p in passes for n, a, b in p.phases if n == ph), [e for e in ends if e is not None])
    return {"phases": totals, "passes": per_pass}


def swept_cells(band, ports_W: np.ndarray, sweep_mm: float) -> np.ndarray:
    """(n_rings, n_az) bool: the cutter port (positions ports_W (K, 3) mm, W, densely
    sampled) passed within half a sweep width of the cell's shaving target."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(ports_W).query(band.target_W.reshape(-1, 3))
    return (d <= 0.5 * sweep_mm).reshape(band.reason.shape)


def sweep_ports_W(robot, run, passes: list[ExecutedPass]) -> np.ndarray:
    """(K, 3) mm: where the cutter port was (frame W) at every 5th control step of the
    `run` of `passes` spent in a sweep (what swept_cells takes)."""
    _, step_phase = step_phases(run, passes)
    return np.array([robot.pose("P", q)[1] for q in run.q[step_phase == "sweep"][::5]]).reshape(-1, 3)


@dataclass(frozen=True, eq=False)
class ExecutionFigures:
    """What execution_figures measured: `figures` (plan.json's keys, JSON-ready), the band's
    cells `swept` (n_rings, n_az) bool (the cutter port within half a sweep width of the
    cell's target during the sweeps) and the cutter port's positions `sweep_ports_W`
    (K, 3) mm, frame W, every 5th control step of the sweeps (sweep_ports_W's)."""

    figures: dict
    swept: np.ndarray
    sweep_ports_W: np.ndarray


def execution_figures(robot, run, passes: list[ExecutedPass], plan, sweep_mm: float, d_safe_mm: float,
                      eye) -> ExecutionFigures:
    """What the closed-loop `run` of the plan's `passes` did (ExecutionFigures), the cells
    swept within half a sweep width `sweep_mm` (mm) of their target. Its `figures`:
    `band_coverage` (fraction of all the band's cells swept), `planned_cells_swept` (fraction
    of the planned cells swept; None without one), `min_true_clearance_mm` (mm),
    `violations` (steps more than 0.05 mm inside d_safe_mm (mm) of the true retina),
    `filter_intervention_fraction`, `failsafe_stops`, and `sweep_true_depth_mm` (p5,
    median, p95 in mm of the cutter port's distance from the TRUE retina `eye` while it
    sweeps: the depth the vitreous was shaved at, which on a model that is off differs from
    the planned standoff; None without a sweep)."""
    ports_W = sweep_ports_W(robot, run, passes)
    swept = swept_cells(plan.band, ports_W, sweep_mm)
    planned = plan.port_of >= 0
    depth = eye.signed_distance(ports_W) if len(ports_W) else None
    figures = {"band_coverage": float(swept.mean()),
               "planned_cells_swept": float(swept[planned].mean()) if planned.any() else None,
               "min_true_clearance_mm": float(run.true_clearance_mm.min()),
               "violations": int(np.sum(run.true_clearance_mm < d_safe_mm - 0.05)),
               "filter_intervention_fraction": float(run.intervened.mean()), "failsafe_stops": run.failsafe_stops,
               "sweep_true_depth_mm": None if depth is None else dict(zip(("p5", "median", "p95"),
                                                                          map(float, np.percentile(depth, [5, 50, 95]))))}
    return ExecutionFigures(figures, swept, ports_W)
