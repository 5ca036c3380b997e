"""`vitreoguard plan`: plan the peripheral shaving path on the FITTED eye model and execute
it through the closed loop (safety filter on) against the TRUE eye.

The model is built as the system would build it (spiral scan through the loop); the
band, its reachability from the trocar and the serpentine path come from
planning.peripheral; the path runs as a TipPathCommand (tip positions and port rolls of
the planned joint trajectory). Writes plan.json (coverage, clearances, timing, the reachability
reasons, the second-trocar suggestion and the path's figures), coverage.png (the band
as azimuth x height: why each cell is or is not reachable, and the path) and plan.mcap
(the execution's log).
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import re

import numpy as np

from eval.cli.args import SEED, add_eye_param, choice, eye_params, number
from eval.cli.io import UsageError, prepare_out_dir, save_figure, write_json
from eval.cli.progress import phase
from models.eyes import EYE_SHAPES

REASON_COLORS = {"ok": "tab:green", "lens": "tab:blue", "port": "tab:orange", "reach": "tab:red", "shaft": "tab:purple"}


# planning.peripheral.BandSpec's parameters (named in its messages) -> the flags that set them
FLAG_OF_PARAMETER = {"spacing_mm": "--sweep-mm", "standoff_mm": "--standoff-mm", "tip_speed_mm_s": "--tip-speed-mm-s",
                     "band z_E range": "--band", "z_min": "z0", "z_max": "z1", "z_min_E": "z0", "z_max_E": "z1",
                     "trust_angle_deg": "--trust-angle-deg"}
_PARAMETER = re.compile(r"\b(" + "|".join(sorted(map(re.escape, FLAG_OF_PARAMETER), key=len, reverse=True)) + r")\b")
POSITIVE_MM = number(0.0, None, "mm", lo_open=True)
POSITIVE_MM_S = number(0.0, None, "mm/s", lo_open=True)
TRUST_ANGLE = number(0.0, 180.0, "deg", lo_open=True)


def flags_named(message: str) -> str:
    """`message` with planning's parameter names replaced by the flags that set them."""
    return _PARAMETER.sub(lambda m: FLAG_OF_PARAMETER[m.group(1)], message)


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
    p = sub.add_parser("plan", help="peripheral vitrectomy path on the fitted model, executed through the filter")
    p.add_argument("--shape", type=choice("shape", EYE_SHAPES), default="emmetropic",
                   help=f"true eye: one of {' '.join(EYE_SHAPES)}")
    add_eye_param(p)
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--standoff-mm", type=POSITIVE_MM, default=1.0,
                   help="shaving standoff inside the model, mm: above the filter's boundary + 0.1 mm (0.6 mm for "
                        "the ellipsoid) and at most 5 mm")
    p.add_argument("--band", type=band_range, default="0,5", metavar="Z0,Z1",
                   help="band z_E range 'z0,z1' in mm (equator 0, ora serrata 5); |z_E| below the smallest retinal "
                        "semi-axis minus the standoff")
    p.add_argument("--sweep-mm", type=POSITIVE_MM, default=1.0, help="cutter sweep width = ring spacing, [0.2, 5] mm")
    p.add_argument("--tip-speed-mm-s", type=POSITIVE_MM_S, default=5.0, help="shaving tip speed, [0.1, 20] mm/s")
    p.add_argument("--seed", type=SEED, default=0, help=f"sensor noise seed of the model-building scan, {SEED.range}")
    p.add_argument("--no-execute", action="store_true", help="plan only (no closed-loop execution)")
    p.add_argument("--trust-angle-deg", type=TRUST_ANGLE, default=180.0,
                   help=f"during the shaving the filter trusts the model this far (from the eye centre, "
                        f"{TRUST_ANGLE.range}) from measured directions; beyond, the conservative prior also bounds the "
                        "tip. 180: the band is never measured (the fibre looks along the shaft), so shaving it rests "
                        "on the global model's extrapolation, as planning does; 10, the teleoperation default, holds "
                        "the tip back")
    p.set_defaults(func=main)


def spec_of(args):
    """The planning.peripheral.BandSpec of the flags; UsageError naming the flag at fault."""
    from planning.peripheral import BandSpec
    from safety.margins import SMALLEST_RETINAL_SEMI_AXIS_MM

    z0, z1 = args.band
    try:
        spec = BandSpec(z_min_E=z0, z_max_E=z1, spacing_mm=args.sweep_mm, standoff_mm=args.standoff_mm,
                        tip_speed_mm_s=args.tip_speed_mm_s)
    except ValueError as exc:
        raise UsageError(flags_named(str(exc))) from None
    limit = SMALLEST_RETINAL_SEMI_AXIS_MM - spec.standoff_mm  # checked before any motion; the model re-checks
    if not (-limit < z0 and z1 < limit):
        raise UsageError(f"--band {z0:g},{z1:g} lies outside the model of any eye we simulate "
                         f"(|z_E| must stay below {limit:.2f} mm with a {spec.standoff_mm:g} mm standoff)")
    return spec


def roll_of(robot, q, p_WC) -> float:
    """The instrument's roll about the shaft at q (planning.ik.roll_direction_W convention)."""
    from planning.ik import signed_angle

    R, p = robot.pose("I", q)
    u = R[:, 0]
    h = np.cross([0.0, 0.0, 1.0], u)
    return signed_angle(h / np.linalg.norm(h), R[:, 1], u)


def main(args) -> int:
    spec = spec_of(args)
    args.eye_params = eye_params(args.eye_param, args.shape)
    from eval.experiments.boundary import build_model_by_spiral, run_with_progress
    from eval.closed_loop import LoopConfig, semi_axes_mm
    from eval.cli.boundary import make_loop
    from eval.experiments.command_sources import TipPathCommand
    from eval.log.writer import RunLogger
    from planning import SurgeryScenario
    from planning.ik import IKFailure
    from planning.peripheral import REASONS, coverage, plan_path, second_trocar

    scenario = SurgeryScenario(eye_name=args.shape, eye_params=args.eye_params)
    loop = make_loop(scenario, LoopConfig(trust_angle_deg=args.trust_angle_deg), sensor_seed=args.seed)
    build = build_model_by_spiral(loop, progress=f"spiral scan building the model ({args.shape} eye)")
    trusted = loop.model.snapshot_for(build.model, build.coverage, 0.0)
    if trusted.shape is None:
        radii = semi_axes_mm(build.model.shape)
        raise UsageError(f"cannot plan: the filter does not trust this {build.kind_final} model (semi-axes "
                         f"{', '.join(f'{r:.1f}' for r in radii)} mm; an eye's lie in {loop.config.model_radius_range_mm} "
                         f"mm) and would hold the instrument inside the conservative prior, away from the band")
    model = trusted.shape  # what the filter will bound the motion with (the sphere if the ellipsoid is no eye's)
    boundary = loop.config.filter.d_safe_mm + trusted.margin_mm(loop.config.margins)
    if spec.standoff_mm < boundary + 0.2:
        raise UsageError(f"--standoff-mm {spec.standoff_mm:g} is below the boundary the filter keeps from this "
                         f"{trusted.kind} model ({boundary:.2f} mm + 0.2 mm to shave without the filter "
                         f"stepping in); use at least {boundary + 0.2:.2f} mm")
    spec = dataclasses.replace(spec, boundary_mm=boundary)  # the whole instrument plans outside it
    try:
        with phase("planning the shaving path (band, reachability, joint trajectory)"):
            plan = plan_path(loop.robot, scenario, model, spec)
    except (ValueError, IKFailure) as exc:
        raise UsageError(f"cannot plan: {flags_named(str(exc))}") from None
    out = prepare_out_dir(args.out)
    robot, traj = loop.robot, plan.trajectory
    ts = np.arange(traj.start_time(), traj.end_time(), 0.02)
    Q = traj.vector_values(ts).T
    tips = np.array([robot.pose("T", q)[1] for q in Q])
    band = plan.band
    result = {
        "coverage": coverage(band, tips, spec.spacing_mm),
        "band_reachable": float(band.reachable.mean()),
        "min_model_clearance_mm": float(np.min(model.signed_distance(tips))),
        "min_true_clearance_mm": None,
        "duration_s": float(traj.end_time() - traj.start_time()),
        "path_length_mm": float(np.linalg.norm(np.diff(tips, axis=0), axis=1).sum()),
        "min_joint_margin_deg": float(np.degrees(min(robot.joint_margin_rad(q).min() for q in Q))),
        "filter_intervention_fraction": None,
        "plan_time_s": plan.plan_time_s,
        "shape": args.shape, "eye_params": args.eye_params, "model_kind": trusted.kind, "fitted_kind": build.kind_final, "standoff_mm": spec.standoff_mm,
        "boundary_mm": spec.boundary_mm,
        "trust_angle_deg": args.trust_angle_deg,
        "band_z_E_mm": [spec.z_min_E, spec.z_max_E], "cells": int(band.reason.size),
        "reasons": {r: int(np.sum(band.reason == r)) for r in REASONS},
        "max_port_angle_deg_on_path": float(np.max(band.port_deg[band.reachable])) if band.reachable.any() else None,
        "max_planned_rcm_error_um": float(1e3 * max(robot.rcm_error_mm(q, scenario.p_WC) for q in Q)),
        "second_trocar": second_trocar(robot, scenario, band, spec),
    }
    if not args.no_execute:
        roll = np.unwrap([roll_of(robot, q, scenario.p_WC) for q in Q])
        command = TipPathCommand(ts - ts[0], tips, roll_rad=roll)
        with RunLogger(out / "plan.mcap", loop.config.filter, metadata={"shape": args.shape, "run": "peripheral plan"}) as log:
            run = run_with_progress(loop, command, Q[0], result["duration_s"] + 0.2, "shaving through the closed loop",
                                    model=build.model, coverage=build.coverage, logger=log)
        result["min_true_clearance_mm"] = float(run.true_clearance_mm.min())
        result["filter_intervention_fraction"] = float(run.intervened.mean())
        result["execution"] = {"failsafe_stops": run.failsafe_stops, "max_rcm_error_um": float(1e3 * np.nanmax(run.rcm_error_mm)),
                               "realtime_factor": run.realtime_factor,
                               "executed_coverage": coverage(band, np.array([robot.pose("T", q)[1] for q in run.q[::20]]),
                                                             spec.spacing_mm)}
    save_figure(_coverage_figure(band, tips, scenario, args.shape, result), out / "coverage.png")
    write_json(out / "plan.json", result)
    for key in ("coverage", "band_reachable", "min_model_clearance_mm", "min_true_clearance_mm", "duration_s",
                "path_length_mm", "min_joint_margin_deg", "filter_intervention_fraction", "plan_time_s"):
        v = result[key]
        print(f"{key:30s} {v:.4g}" if isinstance(v, float) else f"{key:30s} {v}")
    print(f"wrote {out / 'plan.json'}, {out / 'coverage.png'}" + ("" if args.no_execute else f", {out / 'plan.mcap'}"))
    return 0


def _coverage_figure(band, tips, scenario, shape: str, result: dict):
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11, 4))
    A, Z = np.meshgrid(np.degrees(band.azimuth), band.z_E)
    for reason, color in REASON_COLORS.items():
        m = band.reason == reason
        ax.scatter(A[m], Z[m], s=28, marker="s", color=color, label=f"{reason} ({int(m.sum())})")
    P_E = scenario.eye_pose.to_E(tips)
    az = np.degrees(np.arctan2(P_E[:, 1], P_E[:, 0])) % 360.0
    jumps = np.abs(np.diff(az)) > 180.0
    az_plot = np.where(np.concatenate([[False], jumps]), np.nan, az)
    ax.plot(az_plot, P_E[:, 2], color="k", lw=0.8, label="planned tip path")
    ax.set_xlabel("azimuth in the eye frame (deg)")
    ax.set_ylabel("height z_E (mm): equator 0, ora serrata 5")
    st = result["second_trocar"]
    extra = "" if st["azimuth_deg"] is None else f"; a second trocar at {st['azimuth_deg']:.0f} deg adds {st['adds_fraction']:.0%}"
    ax.set_title(f"{shape}: reachable {result['band_reachable']:.0%} of the band, coverage {result['coverage']:.0%}{extra}",
                 fontsize=9)
    ax.legend(fontsize=7, loc="upper right", ncol=5)
    fig.tight_layout()
    return fig
