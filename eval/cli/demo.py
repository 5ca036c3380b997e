"""`vitreoguard demo`: the closed loop on the default eye, end to end.

The Meca500 scans a spiral through the trocar while the simulated iiOCT feeds the
adaptive model (prior -> sphere -> ellipsoid -> ellipsoid + local detail), then an
adversarial "surgeon" attacks the retina, the port side and the lens while the safety
filter holds the boundary: 0.5 mm + 3 sigma of the local-global model.
Prints the model's history and the boundary's summary; writes demo.json (boundary.json's
keys + the history), the plots and the MCAP logs (open them in Foxglove).
"""
from __future__ import annotations

import argparse

import numpy as np

from eval.cli.args import SEED, choice, integer, out_dir
from eval.cli.io import prepare_out_dir, write_json
from models.eyes import EYE_SHAPES

SCENARIOS = integer(1, 1000)
ROWS = integer(2, 1000)


def register(sub) -> None:
    p = sub.add_parser("demo", help="closed loop on the default eye: spiral scan, transition, adversarial teleoperation")
    p.add_argument("--out", type=out_dir, default="out/demo", help="output directory")
    p.add_argument("--shape", type=choice("shape", EYE_SHAPES), default="emmetropic",
                   help=f"true eye: one of {' '.join(EYE_SHAPES)}")
    p.add_argument("--seed", type=SEED, default=0, help=f"seed of the sensor noise, starts and adversary, {SEED.range}")
    p.add_argument("--scenarios", type=SCENARIOS, default=20,
                   help=f"adversarial scenarios of 0.5 s after the scan, {SCENARIOS.range}")
    p.add_argument("--rows", type=ROWS, default=10, help=f"rows of the model history table, {ROWS.range}")
    p.add_argument("--meshcat", action="store_true",
                   help="then replay the scan and the first 3 scenarios in Meshcat (robot, true retina, model and "
                        "boundary as they changed, beam, tip path) and wait")
    p.set_defaults(func=main)


def _history_rows(build, rows: int) -> list[dict]:
    """The model at `rows` instants of the scan: time, kind the filter used, points, radii."""
    run, history = build.run, build.model.history
    out = []
    for k in np.linspace(0, len(run.t) - 1, rows).round().astype(int):
        t = float(run.t[k])
        n = int(round(len(history) * t / run.t[-1]))
        u = history[min(max(n - 1, 0), len(history) - 1)] if history else None
        out.append({"t_s": t, "kind": run.kind[k], "n_points": 0 if u is None else u.n_points,
                    "scan_range_mm": 0.0 if u is None else float(u.scan_range_mm),
                    "sphere_radius_mm": None if u is None or not np.isfinite(u.sphere_radius) else float(u.sphere_radius),
                    "ellipsoid_radii_mm": None if u is None or u.ellipsoid_radii is None
                    else sorted(map(float, u.ellipsoid_radii), reverse=True),
                    "min_true_clearance_mm": float(run.true_clearance_mm[k])})
    return out


def main(args) -> int:
    out = prepare_out_dir(args.out)
    from eval.cli.boundary import plots_written, run_boundary, speed_line
    from eval.experiments.boundary import SPIRAL_REVOLUTIONS, SPIRAL_SPEED_MM_S

    boundary_args = argparse.Namespace(shape=args.shape, scenarios=args.scenarios, sphere_scenarios=0, seed=args.seed,
                                       duration_s=0.5, spiral_speed_mm_s=SPIRAL_SPEED_MM_S, spiral_revolutions=SPIRAL_REVOLUTIONS,
                                       sensor_mode="distance", eye_params={})
    print(f"VitreoGuard demo: closed loop on the {args.shape} eye (Meca500 through the trocar, iiOCT at 2 kHz, "
          "filter at 1 kHz)")
    boundary = run_boundary(boundary_args, out, keep_build=True)
    result, build = boundary.result, boundary.build
    rows = _history_rows(build, args.rows)
    print(f"\nModel during the spiral scan ({build.run.duration_s:.1f} s, {build.model.n_points} points):")
    print(f"{'t (s)':>6} {'filter uses':>11} {'points':>7} {'range':>8} {'sphere r':>8} {'ellipsoid radii (mm)':>22} {'true clr':>8}")
    for r in rows:
        radii = " ".join(f"{v:6.3f}" for v in r["ellipsoid_radii_mm"]) if r["ellipsoid_radii_mm"] else "-"
        sphere = f"{r['sphere_radius_mm']:8.3f}" if r["sphere_radius_mm"] else f"{'-':>8}"
        print(f"{r['t_s']:6.2f} {r['kind']:>11} {r['n_points']:7d} {r['scan_range_mm']:6.2f}mm {sphere} {radii:>22} "
              f"{r['min_true_clearance_mm']:6.2f}mm")
    m = result["model"]
    print(f"final: {m['kind']}, MAE {m['mae_um']:.1f} um (exact, vs the true retina; ellipsoid fit {m['ef_mae_um']:.1f}, "
          f"sphere fit {m['sf_mae_um']:.1f} um)")
    if m.get("sigma3_coverage") is not None:  # the local model's sigma: at the end and at worst during the scan
        way = m.get("on_the_way") or {}
        during = f", at worst {way['lowest_sigma3_coverage']:.3f} during the scan" if way.get("probes") else ""
        print(f"  3-sigma coverage of the true retina {m['sigma3_coverage']:.3f}{during} (the filter keeps d_safe + 3 sigma)")
    print(f"\nAdversarial teleoperation: {result['scenarios']} scenarios of 0.5 s")
    for key in ("violations", "contacts", "min_true_clearance_mm", "intervention_fraction", "failsafe_stops",
                "realtime_factor", "realtime_factor_unlogged"):
        v = result[key]
        print(f"  {key:24s} {v:.4g}" if isinstance(v, float) else f"  {key:24s} {v}")
    print(f"  {'filter solve (us)':24s} median {result['solve_us']['median']:.0f}, p99 {result['solve_us']['p99']:.0f} "
          f"(Drake DoDifferentialInverseKinematics p99 {result['drake_diffik_us']['p99']:.0f})")
    print(f"  {'filter replayed (us)':24s} {speed_line(result)}")
    write_json(out / "demo.json", {**result, "history": rows})
    print(f"\nwrote {out / 'demo.json'}, plots {', '.join(plots_written(out))}, "
          f"MCAP logs {out / 'spiral.mcap'} and {out / 'boundary.mcap'} (open in Foxglove; "
          f"`vitreoguard replay {out / 'boundary.mcap'}` re-runs the filter)")
    if args.meshcat:
        from eval.loop_view import show_loop

        loop = boundary.loop
        url = show_loop(loop.robot, [build.run, *boundary.campaign.runs[:3]], loop.config.margins,
                        loop.config.filter.d_safe_mm, loop.prior, eye=loop.scenario.eye)
        input(f"Meshcat at {url} (press play on the recording): press Enter to quit ")
    return 0
