"""The virtual-boundary experiment: build the eye model with the spiral scan through the
closed loop, then run seeded adversarial scenarios against it and measure, on the TRUE
eye, how close the instrument came.

Units: mm, s, rad (times in us where named); frame W.
"""
from __future__ import annotations

import copy
import math
from collections import Counter
from dataclasses import dataclass, field, replace

import numpy as np

from eval.closed_loop import ClosedLoop, LoopRun
from eval.experiments.campaign import Workers, run_tasks, scenario_seed
from eval.experiments.command_sources import PACE_FLOOR, AdversarialCommand, PacedTipPath, TipPathCommand
from eval.experiments.model_report import BuildHonesty
from eval.cli.progress import progress_bar
from models.metrics import mae_exact
from models.scan.spiral import PAPER_PITCH_MM, PAPER_REVOLUTIONS
from planning import IKFailure, SurgeryScenario, start_posture
from safety.stack import CORRECTION_EASED, RECOVERY_HELD, relaxations

VIOLATION_MM = 0.45  # true clearance below this is a violation (0.5 mm boundary, 50 um tolerance)
# The model-building spiral: the paper's (models.scan.spiral: pitch 0.5 mm, 18 revolutions, 9 mm in radius in the
# coronal plane), at 15 mm/s through the loop (34 s). With 6 revolutions (pitch 1.5 mm, 11 s) its rings lay
# 10-25 deg apart on the retina, and between them the local model missed a detachment's flank or a staphyloma's
# rim by up to 0.5 mm (scanned p95 235-364 um, seed 0); at the paper's pitch they lie a few degrees apart.
SPIRAL_REVOLUTIONS = PAPER_REVOLUTIONS
SPIRAL_RADIUS_MM = PAPER_PITCH_MM * PAPER_REVOLUTIONS
SPIRAL_SPEED_MM_S = 15.0
SPHERE_PHASE_TURNS = 0.25  # the sphere phase's model: the spiral's first quarter of its turns (2.25 mm of its radius)


def spiral_pitch_mm(revolutions: float) -> float:
    """The pitch (mm) of the model-building spiral of `revolutions` over its SPIRAL_RADIUS_MM."""
    return SPIRAL_RADIUS_MM / revolutions

SCENARIO_S = 0.5
START_DEPTH_MM = (1.5, 4.0)  # adversarial start: tip this far inside the model


@dataclass(frozen=True)
class SpiralBuild:
    """The model built by the spiral through the loop and how the scan went."""

    model: object  # models.AdaptiveEyeModel, in W
    coverage: object  # models.adaptive.coverage.DirectionCoverage of its points
    run: LoopRun
    kind_final: str
    transition_at: float | None  # fraction of the spiral's duration, or None
    ef_mae_um: float
    sf_mae_um: float
    samples: int = 0  # the sensor's samples during the scan
    oblique_samples: int = 0  # valid samples not taken in: their beam met the filter's model beyond the sensor's limit
    honesty: dict | None = None  # the local model's sigma on the way (eval.experiments.model_report.BuildHonesty)


def spiral_path_W(scenario: SurgeryScenario, pitch_mm: float, revolutions: float, spacing_mm: float = 0.1) -> np.ndarray:
    """(N, 3) mm: the scenario's spiral (planning.scenario) in W."""
    return scenario.eye_pose.to_W(scenario.spiral_E(pitch_mm, revolutions, spacing_mm))


class _SimTimeProgress:
    """A command source that advances a progress bar by each whole second of its own clock
    (the path's, `source.path_time_s`, when it has one; else simulation time) and otherwise
    is `source`."""

    def __init__(self, source, bar):
        self._source, self._bar, self._next_s = source, bar, 1.0

    @property
    def finished(self) -> bool | None:
        return getattr(self._source, "finished", None)

    def __call__(self, t_s: float, p_WT, q):
        out = self._source(t_s, p_WT, q)
        while getattr(self._source, "path_time_s", t_s) >= self._next_s:
            self._bar.update(1)
            self._next_s += 1.0
        return out


def run_with_progress(loop: ClosedLoop, source, q0, duration_s: float, desc: str | None, progress_s: float | None = None,
                      **run_kwargs) -> LoopRun:
    """loop.run(source, q0, duration_s, **run_kwargs) with a progress bar labelled `desc`
    over `progress_s` (default duration_s) seconds of the source's clock (none when `desc`
    is None)."""
    if desc is None:
        return loop.run(source, q0, duration_s, **run_kwargs)
    with progress_bar(math.ceil(progress_s or duration_s), f"{desc}, s of the path", unit="s") as bar:
        return loop.run(_SimTimeProgress(source, bar), q0, duration_s, **run_kwargs)


def build_model_by_spiral(loop: ClosedLoop, speed_mm_s: float = SPIRAL_SPEED_MM_S,
                          pitch_mm: float = spiral_pitch_mm(SPIRAL_REVOLUTIONS),
                          revolutions: float = SPIRAL_REVOLUTIONS, logger=None, truth_grid: int = 100,
                          progress: str | None = None, sensor_seed=None) -> SpiralBuild:
    """Scan the spiral (pitch, revolutions) at `speed_mm_s` through `loop` from the IK
    posture at its start, building a fresh AdaptiveEyeModel from the sensor's points. With
    the loop's declared actuator not ideal (delay, lag, acceleration limit: LoopConfig's
    `actuator`) the spiral is a PacedTipPath, whose clock slows while the tip lags its
    reference, and the run ends with the path (at most 1 / PACE_FLOOR times its duration);
    with the ideal actuator it is the timed TipPathCommand (why, measured: README, the
    robot-errors section: under a lag the paced spiral's models are the better ones; with
    the ideal actuator the paced clock, slowed where the boundary holds the tip, leaves
    worse models on the 3 mm staphyloma and the 4 mm pointed apex);
    MAEs in the exact form against a truth_grid^2 sampling of the true retina.
    `progress`: the label of a progress bar (eval.cli.progress, stderr) over the scan's
    simulated seconds, or None for none. `sensor_seed`: the sensor's draws start from it
    (ClosedLoop.run; None: they go on from the loop's previous run)."""
    scenario = loop.scenario
    P = spiral_path_W(scenario, pitch_mm, revolutions)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    # no hold at the start: a still beam adds nothing but lets the floaters that land within
    # the gate's jump limit of the retina pile up on one line before the model can judge them
    times = s / speed_mm_s
    paced = not loop.config.actuator.ideal
    path = PacedTipPath(times, P) if paced else TipPathCommand(times, P)
    q0 = start_posture(loop.robot, P[0], scenario.p_WC)
    model, coverage = loop.new_model(), loop.new_coverage()
    cap_s = float(times[-1]) / PACE_FLOOR + path.settle_s if paced else float(times[-1])  # the paced path's slowest
    watch = loop.model.on_snapshot = BuildHonesty(scenario.eye) if model.local is not None else None
    try:
        run = run_with_progress(loop, path, q0, cap_s + 0.05, progress, float(times[-1]), model=model,
                                coverage=coverage, logger=logger, sensor_seed=sensor_seed)
    finally:
        loop.model.on_snapshot = None
    run = replace(run, wall_s=run.wall_s - loop.model.observer_wall_s)  # the scan's own, without the probes
    truth = scenario.eye.reference_samples(truth_grid, truth_grid)
    trans = _transition_fraction(run, path)
    return SpiralBuild(model, coverage, run, model.kind,
                       trans, 1e3 * mae_exact(model.ellipsoid, truth).mean if model.ellipsoid is not None else float("nan"),
                       1e3 * mae_exact(model.sphere, truth).mean, loop.model.n_samples, loop.model.n_oblique,
                       None if watch is None else watch.summary())


def _transition_fraction(run: LoopRun, path: TipPathCommand) -> float | None:
    """Fraction of the spiral (on its path's clock) done when the model switched (from the
    filter's record of the model kind)."""
    k = next((i for i, kind in enumerate(run.kind) if kind == "ellipsoid"), None)
    return None if k is None else path.path_fraction(float(run.t[k]))


def adversarial_starts(loop: ClosedLoop, model_shape, n: int, rng: np.random.Generator) -> list:
    """n start postures (6,) rad: tip at a random point START_DEPTH_MM inside the model
    and inside the true retina (whichever wall is nearer along a uniform direction from
    the eye centre, posterior of the trocar plane: a surgeon's instrument starts clear
    of the real retina even where the model is off), reachable through the trocar with
    the shaft clear of the lens."""
    out = []
    tries = 0
    while len(out) < n:
        tries += 1
        if tries > 50 * n + 100:
            raise RuntimeError(f"found only {len(out)} of {n} reachable adversarial starts")
        u_E = rng.standard_normal(3)
        u_E /= np.linalg.norm(u_E)
        if u_E[2] > 0.3:  # in front of the trocar plane (start_at), drawn again
            continue
        q = start_at(loop, model_shape, u_E, rng.uniform(*START_DEPTH_MM))
        if q is not None:
            out.append(q)
    return out


def start_at(loop: ClosedLoop, model_shape, u_E, depth_mm: float):
    """The start posture (6,) rad with the tip `depth_mm` inside the nearer of the model and
    the true retina along the unit direction u_E (E) from the eye centre, or None where
    that start is not allowed (u_E[2] > 0.3: in front of the trocar plane, the shaft would
    run along the lens) or not reachable with 3 deg to every joint limit."""
    scenario, robot = loop.scenario, loop.robot
    u_E = np.asarray(u_E, dtype=float)
    if u_E[2] > 0.3:
        return None
    c = scenario.eye_pose.p_WE
    u = scenario.eye_pose.R_WE @ u_E
    wall = min(float(model_shape.ray_cast(c[None], u[None])[0]), float(scenario.eye.ray_cast(c[None], u[None])[0]))
    p = c + max(wall - depth_mm, 0.0) * u
    try:
        scenario.tip_targets_W(scenario.eye_pose.to_E(p[None]))
        q = start_posture(robot, p, scenario.p_WC)
    except (ValueError, IKFailure):
        return None
    return None if np.min(robot.joint_margin_rad(q)) < np.radians(3.0) else q


# The keys of Campaign.summary() a campaign's report carries (boundary.json, faults.json) and prints:
# its safety, its stops and relaxed steps, its RCM and tracking, its speed (the filter's solve
# times, "solve_us", "drake_diffik_us" and "filter_replay_us", are printed in a line of their own).
CAMPAIGN_KEYS = ("scenarios", "violations", "contacts", "min_true_clearance_mm", "intervention_fraction",
                 "tracking_rmse_mm_s", "failsafe_stops", "stops_by_reason", "infeasible_qp_stops", "recovery_held_steps",
                 "correction_eased_steps", "max_rcm_error_um", "realtime_factor", "realtime_factor_unlogged",
                 "bound_over_truth_runs", "max_bound_excess_mm", "bound_excess_true_clearance_mm",
                 "bound_over_truth_in_reach_runs", "max_bound_excess_in_reach_mm")


@dataclass
class Campaign:
    """Adversarial runs against one model (a phase), summarised by `summary()`."""

    runs: list = field(default_factory=list)
    min_clearance_per_run: list = field(default_factory=list)

    def add(self, run: LoopRun) -> None:
        self.runs.append(run)
        self.min_clearance_per_run.append(float(np.min(run.true_clearance_mm)) if len(run.t) else np.inf)

    def summary(self) -> dict:
        runs = self.runs
        mins = np.array(self.min_clearance_per_run)
        steps = sum(len(r.t) for r in runs)
        intervened = sum(int(r.intervened.sum()) for r in runs)
        free = np.concatenate([_free_errors(r) for r in runs]) if runs else np.zeros(0)
        solve = np.concatenate([r.solve_us[r.ok] for r in runs]) if runs else np.zeros(0)
        drake = np.concatenate([r.drake_diffik_us for r in runs]) if runs else np.zeros(0)
        replay = np.concatenate([r.filter_replay_us for r in runs]) if runs else np.zeros(0)
        sim, wall = _simulated_and_wall_s(runs)
        sim_unlogged, wall_unlogged = _simulated_and_wall_s([r for r in runs if not r.logged])
        free_rel = np.concatenate([r.free_tracking_error() for r in runs]) if runs else np.zeros(0)
        relaxed = Counter(w for r in runs for x in r.reasons if x != "ok" for w in relaxations(x))
        return {
            "scenarios": len(runs),
            "violations": int(np.sum(mins < VIOLATION_MM)),
            "contacts": int(np.sum(mins <= 0.0)),
            "min_true_clearance_mm": float(mins.min()) if len(mins) else None,
            "intervention_fraction": intervened / steps if steps else 0.0,
            "tracking_rmse_mm_s": float(np.sqrt(np.mean(free**2))) if len(free) else 0.0,
            "failsafe_stops": int(sum(r.failsafe_stops for r in runs)),
            "stops_by_reason": stops_by_reason(runs),
            "infeasible_qp_stops": infeasible_stops(runs),
            # accepted steps that held their recovering points, and that eased the trocar's drift correction,
            # instead of an infeasible QP's stop (safety.stack)
            "recovery_held_steps": relaxed[RECOVERY_HELD],
            "correction_eased_steps": relaxed[CORRECTION_EASED],
            "solve_us": _quantiles(solve),
            "drake_diffik_us": _quantiles(drake),
            "filter_replay_us": _quantiles(replay),
            "realtime_factor": sim / wall if wall > 0 else None,
            # the same without the run logged step by step for replay (the first)
            "realtime_factor_unlogged": sim_unlogged / wall_unlogged if wall_unlogged > 0 else None,
            "free_tracking_error_p99": float(np.percentile(free_rel, 99)) if len(free_rel) else 0.0,
            "lens_violations": int(sum(np.min(r.lens_clearance_mm) < 0.0 for r in runs)),
            "max_rcm_error_um": float(1e3 * max(np.nanmax(r.rcm_error_mm) for r in runs)) if runs else None,
            **_bound_summary(runs),
        }


def _bound_summary(runs: list) -> dict:
    """The barrier's premise over LoopRuns (LoopRun.bound_excess_mm): in how many runs the
    bound on a monitored point's true clearance that the filter assumed (h - k sigma - c)
    lay over the true clearance at some step, the largest such excess (mm; < 0: the
    smallest margin by which the bounds held) and the true clearance where it was (mm);
    the same over the bounds within the barrier's reach of d_safe (the rows that could act).
    None without a bound."""
    out = {}
    for suffix, key in (("", "bound_excess_mm"), ("_in_reach", "bound_excess_in_reach_mm")):
        finite = [getattr(r, key) for r in runs if np.isfinite(getattr(r, key))]
        out[f"bound_over_truth{suffix}_runs"] = int(sum(x > 0.0 for x in finite))
        out[f"max_bound_excess{suffix}_mm"] = float(max(finite)) if finite else None
    worst = max((r for r in runs if np.isfinite(r.bound_excess_mm)), key=lambda r: r.bound_excess_mm, default=None)
    out["bound_excess_true_clearance_mm"] = None if worst is None else float(worst.bound_excess_clearance_mm)
    return out


def reason_class(reason: str) -> str:
    """A stop's reason without its numbers: the text before its first ':' ("stale sensor"),
    or the whole reason for the QP's ("QP: infeasible")."""
    head = reason.split(":", 1)[0].strip()
    return reason.strip() if head == "QP" else head


def stops_by_reason(runs: list) -> dict:
    """{reason class: failsafe stops} over LoopRuns (a stop: a run of consecutive refused steps,
    counted by its first step's reason)."""
    out: dict = {}
    for r in runs:
        bad = ~r.ok
        for k in np.flatnonzero(bad & ~np.concatenate([[False], bad[:-1]])):
            key = reason_class(r.reasons[k])
            out[key] = out.get(key, 0) + 1
    return dict(sorted(out.items()))


def infeasible_stops(runs: list) -> dict:
    """{"total": runs of consecutive steps at which the filter found no feasible velocity
    (reason "QP: ..."), also those inside a stop for another reason; "after_accepted_step":
    those whose previous step the filter accepted}: at that step a planned stop (zero
    command, the fastest braking the actuator allows) was possible, and the filter moved on
    into a state without a feasible velocity instead. The others follow a refused step (a
    planned stop that could not keep the state feasible) or start the run."""
    total = after = 0
    for r in runs:
        qp = np.array([reason_class(x).startswith("QP") for x in r.reasons], dtype=bool)
        for k in np.flatnonzero(qp & ~np.concatenate([[False], qp[:-1]])):
            total += 1
            after += int(k > 0 and r.ok[k - 1])
    return {"total": total, "after_accepted_step": after}


def _simulated_and_wall_s(runs: list) -> tuple[float, float]:
    """(simulated s, wall s of their simulations) over LoopRuns."""
    return sum(r.duration_s for r in runs), sum(r.wall_s for r in runs)


def _free_errors(run: LoopRun) -> np.ndarray:
    """|v_tip - v_cmd| (mm/s) on the steps where the filter did not intervene."""
    free = run.ok & ~run.intervened
    return np.linalg.norm(run.v_tip[free] - run.v_cmd[free], axis=1)


def _quantiles(x: np.ndarray) -> dict:
    if not len(x):
        return {"median": None, "p99": None}
    return {"median": float(np.median(x)), "p99": float(np.percentile(x, 99))}


@dataclass(frozen=True)
class AdversarialScenario:
    """Scenario `index` of a campaign (a task of eval.experiments.campaign): a start posture,
    an adversary and the sensor's draws from scenario_seed(seed, index), `duration_s` s
    against a copy of `model` and its `coverage`."""

    model: object
    coverage: object
    seed: int
    duration_s: float = SCENARIO_S

    def __call__(self, loop: ClosedLoop, index: int, logger=None) -> LoopRun:
        start, adversary, sensor = scenario_seed(self.seed, index).spawn(3)
        q0 = adversarial_starts(loop, self.model.shape, 1, np.random.default_rng(start))[0]
        scenario = loop.scenario
        command = AdversarialCommand(adversary, scenario.eye_pose.p_WE, scenario.lens_W.center,
                                     loop.config.filter.max_tip_speed_mm_s)
        return loop.run(command, q0, self.duration_s, model=copy.deepcopy(self.model),
                        coverage=copy.deepcopy(self.coverage), logger=logger, sensor_seed=sensor)


def run_campaign(loop: ClosedLoop, model, coverage, n: int, seed: int, duration_s: float = SCENARIO_S,
                 logger=None, log_runs: int = 1, progress=None, workers: Workers | None = None) -> Campaign:
    """n adversarial scenarios (AdversarialScenario) of `duration_s` against copies of
    `model` and its `coverage` (each starts from the same state), seeded per scenario; the
    first `log_runs` run here and go to `logger`, the others run on `workers`
    (eval.experiments.campaign.Workers): the same campaign whatever the workers.
    `progress(done, n)` as scenarios finish."""
    task, workers = AdversarialScenario(model, coverage, int(seed), float(duration_s)), workers or Workers()
    logged = min(n, log_runs) if logger is not None else 0
    runs = [task(loop, i, logger) for i in range(logged)]
    if progress is not None and logged:
        progress(logged, n)
    runs += run_tasks(loop, task, range(logged, n), workers,
                      None if progress is None else (lambda done, total: progress(logged + done, n)))
    campaign = Campaign()
    for run in runs:
        campaign.add(run)
    return campaign
