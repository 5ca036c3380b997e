"""`vitreoguard boundary`: the virtual boundary under attack.

Builds the eye model with a spiral scan through the closed loop (robot, iiOCT sensor,
adaptive model, safety filter), then runs N seeded adversarial scenarios against it and
writes boundary.json (the campaign's figures, the sphere phase and the spiral), the
plots boundary_clearance.png and boundary_activity.png, and the MCAP logs spiral.mcap
(the model-building scan) and boundary.mcap (the first adversarial scenario);
`vitreoguard replay` re-runs their filter steps.
"""
from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from eval.cli.args import SEED, add_eye_param, choice, eye_params, integer, number, out_dir
from eval.cli.boundary_all import ALL, run_all
from eval.cli.io import prepare_out_dir, save_figure, write_json
from eval.cli.loop_flags import add_loop_flags, loop_config, loop_record, scenario
from eval.cli.progress import phase, progress_bar
from eval.cli.workers import add_worker_flags, workers_of
from eval.experiments.boundary import (CAMPAIGN_KEYS, SPHERE_PHASE_TURNS, SPIRAL_RADIUS_MM, SPIRAL_REVOLUTIONS, SPIRAL_SPEED_MM_S,
                                      spiral_pitch_mm)
from eval.experiments.campaign import LOCAL_RAY
from eval.experiments.model_report import error_sigma_figure, model_summary
from models.eyes import EYE_SHAPES

COMPILE_PHASE = "compiling / loading the control loop's kernels"
SCENARIOS = integer(1, 100_000)
SPHERE_SCENARIOS = integer(0, 100_000)
DURATION_S = number(0.05, 10.0, "s")
SPIRAL_SPEED = number(1.0, 17.0, "mm/s")
REVOLUTIONS = number(1.0, 18.0, "revolutions")
SEARCH_BUDGET = integer(1, 1_000_000)


def register(sub) -> None:
    p = sub.add_parser("boundary", help="spiral-built model + N adversarial scenarios: boundary.json, plots, MCAP")
    p.add_argument("--shape", type=choice("shape", (*EYE_SHAPES, ALL)), default="emmetropic",
                   help=f"true eye: one of {' '.join(EYE_SHAPES)}, or {ALL}: every shape, each into OUT/<shape> "
                        "(eval.cli.boundary_all)")
    add_eye_param(p)
    p.add_argument("--scenarios", type=SCENARIOS, default=100,
                   help=f"adversarial scenarios once the model is built, {SCENARIOS.range}")
    p.add_argument("--sphere-scenarios", type=SPHERE_SCENARIOS, default=None,
                   help=f"scenarios in the sphere phase (model from the spiral's first quarter of turns), "
                        f"{SPHERE_SCENARIOS.range}; default min(--scenarios, 50)")
    p.add_argument("--seed", type=SEED, default=0, help=f"seed of starts, adversaries and sensor noise, {SEED.range}")
    p.add_argument("--duration-s", type=DURATION_S, default=0.5, help=f"length of one scenario, {DURATION_S.range}")
    p.add_argument("--spiral-speed-mm-s", type=SPIRAL_SPEED, default=SPIRAL_SPEED_MM_S,
                   help=f"tip speed of the model-building spiral, {SPIRAL_SPEED.range}")
    p.add_argument("--spiral-revolutions", type=REVOLUTIONS, default=SPIRAL_REVOLUTIONS,
                   help=f"revolutions of the model-building spiral over its {SPIRAL_RADIUS_MM:g} mm radius, {REVOLUTIONS.range}")
    p.add_argument("--sensor-mode", choices=("distance", "ascan"), default="distance",
                   help="iiOCT in the loop: extractor error model (fast) or full A-scans")
    p.add_argument("--adversary", choices=("random", "search"), default="random",
                   help="random: the seeded random campaign only; search: then the cross-entropy search "
                        "(eval.experiments.search_adversary) for the smallest true clearance")
    p.add_argument("--search-budget", type=SEARCH_BUDGET, default=None,
                   help=f"simulations of the search adversary, {SEARCH_BUDGET.range}; default 10 x --scenarios")
    add_loop_flags(p)
    p.add_argument("--out", type=out_dir, default="out/boundary", help="output directory")
    add_worker_flags(p)
    p.set_defaults(func=main)


def validate(args) -> None:
    """The defaults that depend on other flags and the eye's shape parameters (the flags'
    ranges are checked while parsing); raises UsageError."""
    args.eye_params = {} if args.shape == ALL else eye_params(args.eye_param, args.shape)
    if args.sphere_scenarios is None:
        args.sphere_scenarios = min(args.scenarios, 50)
    if getattr(args, "search_budget", None) is None:
        args.search_budget = 10 * args.scenarios


class BoundaryRun(NamedTuple):
    """Everything of one `vitreoguard boundary` experiment: boundary.json's content, the
    SpiralBuild, the adversarial Campaign and the ClosedLoop they ran in."""

    result: dict
    build: object
    campaign: object
    loop: object


def make_loop(scenario, config=None, **kwargs):
    """eval.closed_loop.ClosedLoop(scenario, config, **kwargs) under a progress phase: its
    construction compiles the control loop's kernels on a first run (numba, minutes)."""
    from eval.closed_loop import ClosedLoop, LoopConfig

    with phase(COMPILE_PHASE):
        return ClosedLoop(scenario, LoopConfig() if config is None else config, **kwargs)


def speed_line(s: dict) -> str:
    """The filter's compiled step timed after the run on Drake's states (a campaign summary's
    filter_replay_us) and its p99 over Drake's DoDifferentialInverseKinematics p99, so timed
    and as the loop timed it (solve_us: between the simulator's and the model's work)."""
    f, d, live = s["filter_replay_us"], s["drake_diffik_us"], s["solve_us"]
    if f["p99"] is None or d["p99"] is None or live["p99"] is None:
        return "no step timed"
    return (f"median {f['median']:.0f}  p99 {f['p99']:.0f}   (the filter's p99 / Drake's: {f['p99'] / d['p99']:.3f} "
            f"timed alike after the run, {live['p99'] / d['p99']:.3f} with the filter's in the loop)")


def bar_progress(bar):
    """A campaign's progress(done, total) callback that moves the tqdm `bar` to `done`."""
    return lambda done, total: bar.update(done - bar.n)


def run_boundary(args, out, keep_build: bool = False, workers=None):
    """The experiment of `args` (validated); writes logs and plots into `out`; returns
    boundary.json's content (a BoundaryRun with `keep_build`). The scenarios run on
    `workers` (eval.experiments.campaign.Workers; None: this process). Progress goes to stderr."""
    from eval.experiments.boundary import build_model_by_spiral, run_campaign
    from eval.log.writer import RunLogger

    config = loop_config(args, sensor_mode=args.sensor_mode)
    loop = make_loop(scenario(args, eye_params=args.eye_params), config, sensor_seed=args.seed)
    meta = {"shape": args.shape, "eye_params": args.eye_params, "seed": args.seed}
    pitch_mm = spiral_pitch_mm(args.spiral_revolutions)
    with RunLogger(out / "spiral.mcap", config.filter, metadata={**meta, "run": "spiral"}) as log:
        build = build_model_by_spiral(loop, args.spiral_speed_mm_s, pitch_mm=pitch_mm, revolutions=args.spiral_revolutions,
                                      logger=log, progress=f"spiral scan ({args.shape} eye)", sensor_seed=args.seed)
    with RunLogger(out / "boundary.mcap", config.filter, metadata={**meta, "run": "adversarial scenario 0"}) as log, \
            progress_bar(args.scenarios, "adversarial scenarios", unit="scenario") as bar:
        campaign = run_campaign(loop, build.model, build.coverage, args.scenarios, args.seed, args.duration_s, logger=log,
                                progress=bar_progress(bar), workers=workers)
    sphere = None
    if args.sphere_scenarios:
        turns = SPHERE_PHASE_TURNS * args.spiral_revolutions
        partial = build_model_by_spiral(loop, args.spiral_speed_mm_s, pitch_mm=pitch_mm, revolutions=turns,
                                        progress=f"sphere phase: spiral of {turns:g} turns", sensor_seed=[args.seed, 1])
        with progress_bar(args.sphere_scenarios, "sphere-phase scenarios", unit="scenario") as bar:
            sphere_campaign = run_campaign(loop, partial.model, partial.coverage, args.sphere_scenarios, args.seed + 1,
                                           args.duration_s, progress=bar_progress(bar), workers=workers)
        sphere = {"sf_mae_um": partial.sf_mae_um, "model": {**model_summary(loop, partial), "fitted_kind": partial.kind_final},
                  **sphere_campaign.summary()}
    s = campaign.summary()
    spiral = build.run
    result = {
        **{k: s[k] for k in (*CAMPAIGN_KEYS, "solve_us", "drake_diffik_us", "filter_replay_us")},
        "shape": args.shape, "eye_params": args.eye_params, "seed": args.seed, "sensor_mode": args.sensor_mode,
        "scenario_s": args.duration_s, "violation_threshold_mm": 0.45, "loop": loop_record(args, config),
        "lens_violations": s["lens_violations"],
        "free_tracking_error_p99": s["free_tracking_error_p99"],
        "model": {**model_summary(loop, build), "fitted_kind": build.kind_final, "transition_at": build.transition_at,
                  "ef_mae_um": build.ef_mae_um,
                  "sf_mae_um": build.sf_mae_um, "n_points": build.model.n_points,
                  "outliers_rejected": build.model.n_rejected_outliers},
        "spiral": {"duration_s": spiral.duration_s, "min_true_clearance_mm": float(spiral.true_clearance_mm.min()),
                   "intervention_fraction": float(spiral.intervened.mean()),
                   "max_rcm_error_um": float(1e3 * np.nanmax(spiral.rcm_error_mm)),
                   "realtime_factor": spiral.realtime_factor, "failsafe_stops": spiral.failsafe_stops},
        "sphere_phase": sphere,
        "logs": {"spiral": str(out / "spiral.mcap"), "scenario_0": str(out / "boundary.mcap")},
    }
    if getattr(args, "adversary", "random") == "search":
        result["search"] = run_search(args, loop, build, s["min_true_clearance_mm"], workers)
        result["worst_found_clearance_mm"] = result["search"]["worst_found_clearance_mm"]
    save_figure(_clearance_figure(campaign, args.shape), out / "boundary_clearance.png", tight_bbox=False)
    fig = error_sigma_figure(loop, build)
    if fig is not None:
        save_figure(fig, out / "model_error_sigma.png")
    save_figure(_activity_figure(campaign, s), out / "boundary_activity.png", tight_bbox=False)
    return BoundaryRun(result, build, campaign, loop) if keep_build else result


def run_search(args, loop, build, random_min_mm: float, workers=None) -> dict:
    """The search adversary against the built model, its islands on `workers`:
    boundary.json's "search" entry, with the worst scenario's theta and sensor seed
    (eval.experiments.search_adversary.run_theta replays it) and its clearance when run again."""
    from eval.experiments.search_adversary import cross_entropy_search, run_theta

    with progress_bar(args.search_budget, "search adversary", unit="simulation") as bar:
        found = cross_entropy_search(loop, build.model, build.coverage, args.search_budget, args.seed, args.duration_s,
                                     workers=workers, progress=bar_progress(bar))
    replay = run_theta(loop, build.model, build.coverage, found.worst_theta, args.duration_s, found.worst_sensor_seed)
    return {"budget": args.search_budget, "worst_found_clearance_mm": found.worst_clearance_mm,
            "replayed_clearance_mm": None if replay is None else float(replay.true_clearance_mm.min()),
            "random_min_true_clearance_mm": random_min_mm,
            "violations": int(sum(c < 0.45 for c in found.clearances)),
            "failsafe_stops": found.failsafe_stops, "stops_by_reason": found.stops_by_reason, "restarts": found.restarts,
            "scenario": {"shape": args.shape, "seed": args.seed, "duration_s": args.duration_s,
                         "sensor_seed": found.worst_sensor_seed, "theta": [float(x) for x in found.worst_theta]}}


def write_shape(args, out, workers) -> dict:
    """run_boundary into the folder `out` (made) and its boundary.json; returns the content."""
    out = prepare_out_dir(out)
    result = run_boundary(args, out, workers=workers)
    write_json(out / "boundary.json", result)
    return result


PLOTS = ("boundary_clearance.png", "boundary_activity.png", "model_error_sigma.png")  # write_shape's (the last: a model)


def plots_written(out) -> list[str]:
    """The names of write_shape's plots in `out` (the model's error map only with a model)."""
    return [name for name in PLOTS if (Path(out) / name).exists()]


def main(args) -> int:
    validate(args)
    if args.shape == ALL:
        if args.ray not in (None, LOCAL_RAY):
            workers_of(args)  # the cluster reachable (or refused) before anything is written
        return run_all(args)
    workers = workers_of(args)
    result = write_shape(args, args.out, workers)
    out = Path(args.out)
    print(f"\n{'scenarios':24s} {result['scenarios']}")
    for key in (*CAMPAIGN_KEYS[1:], "worst_found_clearance_mm"):
        if key not in result:
            continue
        v = result[key]
        print(f"{key:24s} {v:.4g}" if isinstance(v, float) else f"{key:24s} {v}")
    print(f"{'solve_us':24s} median {result['solve_us']['median']:.0f}  p99 {result['solve_us']['p99']:.0f}   "
          f"(Drake DoDifferentialInverseKinematics: median {result['drake_diffik_us']['median']:.0f}  "
          f"p99 {result['drake_diffik_us']['p99']:.0f})")
    print(f"{'filter_replay_us':24s} {speed_line(result)}")
    print(f"wrote {out / 'boundary.json'}, {', '.join(plots_written(out))}, spiral.mcap and boundary.mcap (scenario 0)")
    return 0


def _clearance_figure(campaign, shape: str):
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    mins = np.array(campaign.min_clearance_per_run)
    a.hist(mins, bins=40, color="tab:blue")
    a.axvline(0.45, color="r", ls="--", lw=1, label="violation (0.45 mm)")
    a.axvline(0.5, color="k", ls=":", lw=1, label="boundary (0.5 mm)")
    a.set_xlabel("smallest TRUE clearance per scenario (mm)")
    a.set_ylabel("scenarios")
    a.set_title(f"{shape}: {len(mins)} adversarial scenarios")
    a.legend()
    for run in campaign.runs[:8]:
        b.plot(run.t - run.t[0], run.true_clearance_mm, lw=0.8)
    b.axhline(0.5, color="k", ls=":", lw=1)
    b.set_xlabel("time in scenario (s)")
    b.set_ylabel("smallest true clearance of the monitored points (mm)")
    b.set_title("first scenarios")
    fig.tight_layout()
    return fig


def _activity_figure(campaign, summary: dict):
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    frac = [float(r.intervened.mean()) for r in campaign.runs]
    a.hist(frac, bins=30, color="tab:orange")
    a.set_xlabel("fraction of control steps the filter changed the command")
    a.set_ylabel("scenarios")
    a.set_title(f"filter activity (overall {summary['intervention_fraction']:.1%})")
    solve = np.concatenate([r.solve_us[r.ok] for r in campaign.runs])
    drake = np.concatenate([r.drake_diffik_us for r in campaign.runs])
    bins = np.logspace(np.log10(max(min(solve.min(), drake.min() if len(drake) else solve.min()), 1.0)),
                       np.log10(max(solve.max(), drake.max() if len(drake) else solve.max())), 40)
    b.hist(solve, bins=bins, alpha=0.6, label="safety filter QP (all constraints)")
    if len(drake):
        b.hist(drake, bins=bins, alpha=0.6, label="Drake DoDifferentialInverseKinematics")
    b.set_xscale("log")
    b.set_xlabel("solve time per control step (us)")
    b.legend()
    fig.tight_layout()
    return fig
