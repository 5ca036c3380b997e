"""`vitreoguard plan`: plan the shaving of the whole peripheral band (equator to ora serrata,
all the way round) on the FITTED eye model through the ports of a 3-port vitrectomy, and
execute it pass by pass through the closed loop (safety filter on, its RCM on the active
trocar) against the TRUE eye: each pass's insertion from where the instrument is clear
inside the eye, its sweep and its withdrawal back to there (eval.experiments.plan_execution);
the instrument's way through the eye wall at the trocar and the moves between trocars
outside the eye are planned, timed and exported, not simulated.

The model is built as the system would build it (spiral scan through the loop, through
the first port; with --survey-mm, then --survey-passes sweeps of the band that much
deeper, each planned on the model the one before left, whose A-scans the model takes in
before the shaving is planned: eval.cli.plan_model); each cell's reachability from each
port, the assignment of cells to ports, the per-port sweeps and the port switches come
from planning.multiport. Writes
plan.json (band coverage, per-port figures, switches, why cells are not reached,
clearances, timing, the execution per phase and per pass), coverage.png (the band unrolled, each cell coloured by the port
that swept it or the reason it was not reached), plan.mcap (the execution's log),
survey_<k>.mcap (each survey pass's log), plan_trajectory.csv and plan_trajectory/ (a ROS 2 bag, MCAP storage: one
trajectory_msgs/JointTrajectory per port segment).
"""
from __future__ import annotations

import argparse
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from eval.cli.args import SEED, add_eye_param, choice, eye_params, integer, number, out_dir
from eval.cli.io import UsageError, prepare_out_dir, save_figure, write_json
from eval.cli.loop_flags import add_model_flag, loop_config
from eval.cli.plan_model import check_standoff, flags_named, move_logs, plan_on_model, survey_band
from eval.cli.progress import phase
from models.eyes import EYE_SHAPES
from planning.peripheral import SPACING_RANGE_MM, STANDOFF_MAX_MM, TIP_SPEED_RANGE_MM_S
from planning.ports import PARS_PLANA_MM

STANDOFF_MM = number(0.0, STANDOFF_MAX_MM, "mm", lo_open=True)  # its floor, the filter's boundary + 0.2 mm: spec_of
SWEEP_MM = number(*SPACING_RANGE_MM, "mm")
TIP_SPEED = number(*TIP_SPEED_RANGE_MM_S, "mm/s")
TRUST_ANGLE = number(0.0, 180.0, "deg", lo_open=True)
PORT_ANGLE = number(0.0, 90.0, "deg", lo_open=True)
SURVEY_MM = number(0.0, 3.0, "mm")
SURVEY_PASSES = integer(1, 4)
LIMBUS_MM = number(*PARS_PLANA_MM, "mm")  # the pars plana (planning.ports)


def port_clock(text: str) -> tuple[str, float]:
    """Type of --port-clock: 'NAME=HOUR' with HOUR in [1, 12]."""
    from planning.ports import STANDARD_LAYOUT

    names = [n for n, *_ in STANDARD_LAYOUT]
    name, _, hour = text.partition("=")
    if name not in names:
        raise argparse.ArgumentTypeError(f"unknown port {name!r}; choose from {', '.join(names)} (as NAME=HOUR)")
    try:
        h = float(hour)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be NAME=HOUR with HOUR a clock hour in [1, 12], got {text!r}") from None
    if not (math.isfinite(h) and 1.0 <= h <= 12.0):
        raise argparse.ArgumentTypeError(f"clock hour must be in [1, 12], got {hour!r}")
    return name, h


def port_list(text: str) -> tuple[str, ...]:
    """Type of --ports: comma-separated port names of the 3-port layout, each once."""
    from planning.ports import STANDARD_LAYOUT

    names = [n for n, *_ in STANDARD_LAYOUT]
    out = tuple(v.strip() for v in text.split(","))
    for v in out:
        if v not in names:
            raise argparse.ArgumentTypeError(f"unknown port {v!r}; choose from {', '.join(names)}")
    if len(set(out)) != len(out):
        raise argparse.ArgumentTypeError(f"each port at most once, got {text!r}")
    return out


def band_range(text: str) -> tuple[float, float]:
    """Type of --band: 'z0,z1' (mm, finite, z0 < z1)."""
    try:
        z0, z1 = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be 'z0,z1' in mm with z0 < z1, got {text!r}") from None
    if not (math.isfinite(z0) and math.isfinite(z1) and z0 < z1):
        raise argparse.ArgumentTypeError(f"must be 'z0,z1' in mm with finite z0 < z1, got {text!r}")
    return z0, z1


def register(sub) -> None:
    from planning.multiport import DEFAULT_PORTS
    from planning.peripheral import PORT_FACING_MAX_DEG
    from planning.ports import REFERENCE_LIMBUS_MM, SIDES

    p = sub.add_parser("plan", help="peripheral vitrectomy of the whole band through the ports, executed through the filter")
    p.add_argument("--shape", type=choice("shape", EYE_SHAPES), default="emmetropic",
                   help=f"true eye: one of {' '.join(EYE_SHAPES)}")
    add_eye_param(p)
    p.add_argument("--out", type=out_dir, required=True, help="output directory")
    p.add_argument("--standoff-mm", type=STANDOFF_MM, default=1.0,
                   help="shaving standoff inside the model, mm: at least the filter's boundary (0.5 mm + the "
                        "model's margin + the calibration bound's 0.064 mm) + 0.2 mm, and at most 5 mm")
    p.add_argument("--band", type=band_range, default="0,5", metavar="Z0,Z1",
                   help="band z_E range 'z0,z1' in mm (equator 0, ora serrata 5); |z_E| below the smallest retinal "
                        "semi-axis minus the standoff")
    p.add_argument("--sweep-mm", type=SWEEP_MM, default=1.0,
                   help=f"cutter sweep width = ring spacing, {SWEEP_MM.range}")
    p.add_argument("--tip-speed-mm-s", type=TIP_SPEED, default=5.0, help=f"shaving tip speed, {TIP_SPEED.range}")
    p.add_argument("--seed", type=SEED, default=0, help=f"sensor noise seed of the model-building scan, {SEED.range}")
    p.add_argument("--no-execute", action="store_true", help="plan only (no closed-loop execution)")
    p.add_argument("--side", type=choice("eye side", SIDES), default="right", help="which eye: right or left (the "
                   "clock hours of the ports: superotemporal 10 / 2, superonasal 2 / 10, infusion 8 / 4)")
    p.add_argument("--ports", type=port_list, default=",".join(DEFAULT_PORTS), metavar="NAMES",
                   help="the ports the cutter works through, in visiting order (superonasal, superotemporal, infusion: "
                        "the infusion port used as a working port)")
    p.add_argument("--port-clock", type=port_clock, action="append", default=[], metavar="NAME=HOUR",
                   help="a port's clock hour in [1, 12] (the surgeon's view, 12 superior), repeatable")
    p.add_argument("--port-limbus-mm", type=LIMBUS_MM, default=REFERENCE_LIMBUS_MM,
                   help=f"the ports' distance behind the limbus, on the pars plana {LIMBUS_MM.range} (3.0 aphakic, "
                        "3.5 pseudophakic, 4.0 phakic)")
    p.add_argument("--port-angle-deg", type=PORT_ANGLE, default=PORT_FACING_MAX_DEG,
                   help="port rule: the cutter port faces the retina when its normal lies within this angle of the "
                        f"retina's normal, {PORT_ANGLE.range}")
    # the plan keeps to the filter's boundary; the band is never measured before the shaving, and there the local
    # model's sigma is the global model's far from data (README: why the plan's default is the quadric)
    add_model_flag(p, default="quadric")
    p.add_argument("--survey-mm", type=SURVEY_MM, default=0.0,
                   help="first sweep the band this much deeper than --standoff-mm through the same ports, filter on, "
                        "so that the fibre measures the band and the model takes it in; the shaving is then planned "
                        f"on that model. 0: no survey; {SURVEY_MM.range}")
    p.add_argument("--survey-passes", type=SURVEY_PASSES, default=1,
                   help="with --survey-mm: how many times to survey the band, each pass planned on the model the "
                        "previous one left (a pass reaches band the model could not place before it), "
                        f"{SURVEY_PASSES.range}")
    p.add_argument("--trust-angle-deg", type=TRUST_ANGLE, default=180.0,
                   help=f"during the shaving the filter trusts the model this far (from the eye centre, "
                        f"{TRUST_ANGLE.range}) from measured directions; beyond, the conservative prior also bounds the "
                        "tip. 180: the band is never measured (the fibre looks along the shaft), so shaving it rests "
                        "on the global model's extrapolation, as planning does; 10, the teleoperation default, holds "
                        "the tip back")
    p.set_defaults(func=main)


def plan_loop_config(args):
    """The LoopConfig the plan's loop runs with (the survey's and the shaving's filter: the
    quadric boundary's phase margin or, with --model local, the local model's d_safe + k
    sigma; eval.cli.loop_flags.loop_config)."""
    return loop_config(args, trust_angle_deg=args.trust_angle_deg)


def spec_of(args, config):
    """The planning.peripheral.BandSpec of the flags, whose standoff `config` (the plan's
    LoopConfig, plan_loop_config) must keep; UsageError naming the flag at fault."""
    from planning.peripheral import BandSpec
    from safety.margins import SMALLEST_RETINAL_SEMI_AXIS_MM

    z0, z1 = args.band
    check_standoff(args.standoff_mm, config.filter.boundary_mm(0.0),
                   "the filter's boundary without the model's margin (d_safe + the calibration margin)")
    if args.survey_passes > 1 and not args.survey_mm:
        raise UsageError("--survey-passes needs --survey-mm above 0 mm (the survey's depth beyond --standoff-mm)")
    if args.standoff_mm + args.survey_mm > STANDOFF_MAX_MM:
        raise UsageError(f"--standoff-mm {args.standoff_mm:g} + --survey-mm {args.survey_mm:g} puts the survey deeper "
                         f"than {STANDOFF_MAX_MM:g} mm inside the model")
    try:
        spec = BandSpec(z_min_E=z0, z_max_E=z1, spacing_mm=args.sweep_mm, standoff_mm=args.standoff_mm,
                        tip_speed_mm_s=args.tip_speed_mm_s, port_max_deg=args.port_angle_deg)
    except ValueError as exc:
        raise UsageError(flags_named(str(exc))) from None
    limit = SMALLEST_RETINAL_SEMI_AXIS_MM - spec.standoff_mm  # checked before any motion; the model re-checks
    if not (-limit < z0 and z1 < limit):
        raise UsageError(f"--band {z0:g},{z1:g} lies outside the model of any eye we simulate "
                         f"(|z_E| must stay below {limit:.2f} mm with a {spec.standoff_mm:g} mm standoff)")
    return spec


def ports_of(args, eye_name: str, eye_params: dict):
    """(every port of the layout, the ports to work through in visiting order, the first
    one's trocar p_EC mm): UsageError naming the flag at fault."""
    from planning.ports import port_p_EC, standard_ports
    from planning.scenario import default_trocar_E

    try:
        layout = standard_ports(args.side, args.port_limbus_mm, dict(args.port_clock))
    except ValueError as exc:
        flag = "--port-limbus-mm" if "limbus" in str(exc) else "--port-clock"
        raise UsageError(f"{flag}: {exc}") from None
    by_name = {p.name: p for p in layout}
    names = args.ports or tuple(p.name for p in sorted((p for p in layout if p.role == "working"),
                                                       key=lambda p: abs(p.clock_hour - 2.0)))
    visit = tuple(by_name[n] for n in names)
    return layout, visit, port_p_EC(eye_name, visit[0], default_trocar_E(eye_name, eye_params), eye_params)


def outside_loop_margin_deg(robot, plan) -> float | None:
    """The smallest distance (deg) of any joint from its limit on the planned `enter`, `exit`
    and `move` pieces (not run in the loop), sampled as the planner checks them
    (planning.port_moves.LIMIT_CHECK_DT_S); None with no such piece."""
    from planning.port_moves import LIMIT_CHECK_DT_S

    trajs = [(traj, a, b) for seg in plan.segments for n, traj, a, b in seg.pieces() if n in ("enter", "exit")]
    trajs += [(move, move.start_time(), move.end_time()) for move in plan.moves]
    margins = [robot.joint_margin_rad(traj.vector_values(np.append(np.arange(a, b, LIMIT_CHECK_DT_S), b)).T).min()
               for traj, a, b in trajs if b > a]
    return float(np.degrees(min(margins))) if margins else None


def main(args) -> int:
    config = plan_loop_config(args)
    spec = spec_of(args, config)
    args.eye_params = eye_params(args.eye_param, args.shape)
    from eval.experiments.model_report import model_summary
    from eval.cli.boundary import make_loop
    from eval.cli.plan_export import coverage_figure, write_ros2_trajectories, write_trajectory_csv
    from eval.experiments.boundary import build_model_by_spiral
    from eval.experiments.plan_execution import execution_figures, executed_passes, phase_figures, swept_cells
    from eval.log.writer import RunLogger
    from planning import SurgeryScenario
    from planning.multiport import IN_EYE_PHASES, UNREACHABLE
    from planning.scenario import PORTS_EYE_POSE

    layout, visit, p_EC = ports_of(args, args.shape, args.eye_params)
    try:
        scenario = SurgeryScenario(eye_pose=PORTS_EYE_POSE, eye_name=args.shape, eye_params=args.eye_params, p_EC=p_EC,
                                   ports=layout)
    except ValueError as exc:
        raise UsageError(f"--port-clock/--port-limbus-mm: {exc}") from None
    loop = make_loop(scenario, config, sensor_seed=args.seed)
    build = build_model_by_spiral(loop, progress=f"spiral scan building the model ({args.shape} eye, {visit[0].name} port)")
    survey = None
    with tempfile.TemporaryDirectory(prefix="vitreoguard-survey-") as survey_logs:
        if args.survey_mm:
            survey = survey_band(args, loop, build, scenario, visit, spec, Path(survey_logs))
        trusted, model, spec, boundary, plan = plan_on_model(args, loop, build, scenario, visit, spec)
        out = prepare_out_dir(args.out)
        survey_files = move_logs(Path(survey_logs), out)
    robot, band = loop.robot, plan.band
    shape2 = band.reason.shape
    with phase(f"sampling the {len(plan.segments)} passes' in-eye phases (insert, sweep, withdraw)"):
        passes = executed_passes(robot, plan)
    sweeping = [p.phase == "sweep" for p in passes]
    all_tips = np.vstack([p.tips_W[m] for p, m in zip(passes, sweeping)])
    all_Q = np.vstack([p.Q[m] for p, m in zip(passes, sweeping)])
    swept_planned = swept_cells(band, np.array([robot.pose("P", q)[1] for q in all_Q]), spec.spacing_mm)
    durations, planned_s = {}, {}
    for seg in plan.segments:
        durations[seg.port.name] = durations.get(seg.port.name, 0.0) + (seg.insert.end_time() + seg.sweep.trajectory.end_time()
                                                                        + seg.withdraw.end_time())
        mine = planned_s.setdefault(seg.port.name, {})
        for name, _, a, b in seg.pieces():
            mine[name] = mine.get(name, 0.0) + (b - a)
    switch_s = sum(sw.move_s for sw in plan.switches)
    result = {
        "band_coverage": None,
        "band_coverage_planned": float(swept_planned.mean()),
        "planned_cells": int((plan.port_of >= 0).sum()),
        "planned_cells_swept": None,
        "cells": int(band.reason.size),
        "unreachable": {r: int(np.sum((plan.port_of < 0) & (band.reason == r))) for r in UNREACHABLE},
        "ports": {p.name: {"role": p.role, "clock_hour": p.clock_hour, "limbus_mm": p.limbus_mm,
                           "cells_assigned": int((plan.port_of == k).sum()),
                           "reachable_cells": int((plan.reasons_by_port[p.name] == "ok").sum()),
                           "regions": sum(1 for s in plan.segments if s.port.name == p.name),
                           "coverage": None, "duration_s": durations.get(p.name, 0.0),
                           "planned_s": planned_s.get(p.name, {}), "executed_s": None}
                  for k, p in enumerate(plan.ports)},
        "port_switches": sum(1 for sw in plan.switches if sw.from_port != sw.to_port),
        "reentries": sum(1 for sw in plan.switches if sw.from_port == sw.to_port),
        "switches": [{"from": sw.from_port, "to": sw.to_port, "withdraw_s": sw.withdraw_s, "move_s": sw.move_s,
                      "insert_s": sw.insert_s, "duration_s": sw.duration_s,
                      "move_min_outside_mm": sw.move_min_outside_mm} for sw in plan.switches],
        "min_model_clearance_mm": float(np.min(model.retina.signed_distance(all_tips))),
        "min_true_clearance_mm": None,
        "violations": None,
        "duration_s": float(sum(durations.values()) + switch_s),
        "shaving_s": float(sum(s.sweep.trajectory.end_time() for s in plan.segments)),
        "path_length_mm": float(sum(np.linalg.norm(np.diff(p.tips_W[m], axis=0), axis=1).sum() for p, m in zip(passes, sweeping))),
        "min_joint_margin_deg": float(np.degrees(min(robot.joint_margin_rad(q).min() for q in all_Q))),
        "filter_intervention_fraction": None,
        "sweep_true_depth_mm": None,
        "plan_time_s": plan.plan_time_s,
        "shape": args.shape, "eye_params": args.eye_params, "side": args.side, "model_kind": trusted.kind,
        "fitted_kind": build.kind_final,
        "standoff_mm": spec.standoff_mm, "boundary_mm": boundary, "port_angle_deg": spec.port_max_deg,
        "trust_angle_deg": args.trust_angle_deg, "band_z_E_mm": [spec.z_min_E, spec.z_max_E],
        "max_port_angle_deg_on_path": float(np.nanmax(band.port_deg)) if (plan.port_of >= 0).any() else None,
        "max_planned_rcm_error_um": float(1e3 * max(max(robot.rcm_error_mm(q, p.p_WC) for q in p.Q) for p in passes)),
        "outside_loop_s": {name: float(sum(b - a for seg in plan.segments for n, _, a, b in seg.pieces() if n == name))
                           for name in ("enter", "exit")} | {"move": float(switch_s)},
        "min_joint_margin_deg_outside_loop": outside_loop_margin_deg(robot, plan),
        "model": model_summary(loop, build),
        "survey": survey,
    }
    swept = swept_planned
    if not args.no_execute:
        with RunLogger(out / "plan.mcap", loop.config.filter, metadata={"shape": args.shape, "run": "peripheral plan"}) as log:
            with phase(f"executing {len(passes)} passes through the closed loop (insert, sweep, withdraw): "
                       f"{sum(p.duration_s for p in passes):.0f} simulated s"):
                t0 = time.perf_counter()
                run = loop.run_segments([p.segment() for p in passes], model=build.model, coverage=build.coverage, logger=log)
                execution_wall_s = time.perf_counter() - t0
        d_safe = loop.config.filter.d_safe_mm
        figs = phase_figures(robot, run, passes, d_safe)
        executed = execution_figures(robot, run, passes, plan, spec.spacing_mm, d_safe, loop.scenario.eye)
        swept = executed.swept
        for key in ("band_coverage", "planned_cells_swept", "min_true_clearance_mm", "violations",
                    "filter_intervention_fraction", "sweep_true_depth_mm"):
            result[key] = executed.figures[key]
        if survey is not None:  # the whole surgery: the survey's passes and the shaving
            result["filter_intervention_fraction_with_survey"] = (
                (survey["intervened_steps"] + int(np.sum(run.intervened))) / (survey["steps"] + len(run.t)))
            result["min_true_clearance_mm_with_survey"] = min(survey["min_true_clearance_mm"], result["min_true_clearance_mm"])
        for k, p in enumerate(plan.ports):
            mine = plan.port_of == k
            result["ports"][p.name]["coverage"] = float(swept[mine].mean()) if mine.any() else None
            result["ports"][p.name]["executed_s"] = {
                ph: float(sum(f["phases"][ph]["executed_s"] for f in figs["passes"] if f["port"] == p.name and ph in f["phases"]))
                for ph in IN_EYE_PHASES}
        result["phases"], result["passes"] = figs["phases"], figs["passes"]
        result["execution"] = {"failsafe_stops": run.failsafe_stops, "max_rcm_error_um": float(1e3 * np.nanmax(run.rcm_error_mm)),
                               "realtime_factor": run.realtime_factor, "steps": int(len(run.t)),
                               "simulated_s": run.duration_s, "wall_s": execution_wall_s,
                               "samples": loop.model.n_samples, "oblique_samples": loop.model.n_oblique}
    start_ns = time.time_ns()
    write_trajectory_csv(plan, out / "plan_trajectory.csv")
    write_ros2_trajectories(plan, out / "plan_trajectory", start_ns)
    cov = result["band_coverage"] if result["band_coverage"] is not None else result["band_coverage_planned"]
    title = (f"{args.shape} {args.side} eye: band coverage {cov:.0%} through {', '.join(p.name for p in visit)}; "
             f"{result['port_switches']} port switches, {result['reentries']} re-entries")
    save_figure(coverage_figure(plan, swept.reshape(shape2), title), out / "coverage.png")
    write_json(out / "plan.json", result)
    for key in ("band_coverage", "band_coverage_planned", "planned_cells_swept", "port_switches", "min_model_clearance_mm",
                "min_true_clearance_mm", "violations", "duration_s", "filter_intervention_fraction", "plan_time_s"):
        v = result[key]
        print(f"{key:30s} {v:.4g}" if isinstance(v, float) else f"{key:30s} {v}")
    print(f"unreachable                    {result['unreachable']}")
    if result["sweep_true_depth_mm"] is not None:
        d = result["sweep_true_depth_mm"]
        print(f"shaved at (true retina, mm)    p5 {d['p5']:.3f}, median {d['median']:.3f}, p95 {d['p95']:.3f}")
    if survey is not None:
        for k, f in enumerate(survey["passes"], 1):
            print(f"survey {k}  {survey['standoff_mm']:g} mm deep on the {f['model_kind']}: band {f['band_coverage']:.1%}, "
                  f"filter intervened in {f['filter_intervention_fraction']:.2%} of steps, min true clearance "
                  f"{f['min_true_clearance_mm']:.3f} mm, {f['duration_s']:.1f} simulated s")
        if "filter_intervention_fraction_with_survey" in result:
            print(f"with the survey: filter intervened in {result['filter_intervention_fraction_with_survey']:.2%} of steps, "
                  f"min true clearance {result['min_true_clearance_mm_with_survey']:.3f} mm")
    for name, f in result.get("phases", {}).items():
        print(f"{name:9s} executed {f['executed_s']:7.2f} s of {f['planned_s']:7.2f} planned, filter intervened in "
              f"{f['filter_intervention_fraction'] or 0.0:.2%} of steps, min true clearance "
              f"{'-' if f['min_true_clearance_mm'] is None else format(f['min_true_clearance_mm'], '.3f')} mm")
    print(f"wrote {out / 'plan.json'}, {out / 'coverage.png'}, {out / 'plan_trajectory.csv'}, {out / 'plan_trajectory'}"
          + ("" if args.no_execute else f", {out / 'plan.mcap'}") + "".join(f", {f}" for f in survey_files))
    return 0
