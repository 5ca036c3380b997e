"""`vitreoguard demo`: the adaptive model along the paper's spiral on the default eye.

Prints the model's history (kind, radii, accuracy) as a table and writes demo.json
and a Fig. 5-style plot. (When the closed loop lands, the demo becomes it.)
"""
from __future__ import annotations

import numpy as np

from eval.io import UsageError, prepare_out_dir, save_figure, write_json
from eval.paper_figures import fig5
from eval.paper_experiment import run_shape
from models.eyes import EYE_SHAPES


def register(sub) -> None:
    p = sub.add_parser("demo", help="fit the adaptive eye model along the paper's spiral and print its history")
    p.add_argument("--out", default="out/demo", help="output directory (demo.json, demo_mae.png)")
    p.add_argument("--shape", default="emmetropic", help=f"one of: {' '.join(EYE_SHAPES)}")
    p.add_argument("--seed", type=int, default=0, help="noise seed")
    p.add_argument("--rows", type=int, default=12, help="rows of the history table")
    p.set_defaults(func=main)


def main(args) -> int:
    if args.shape not in EYE_SHAPES:
        raise UsageError(f"unknown shape {args.shape!r}; choose from {', '.join(EYE_SHAPES)}")
    if args.rows < 2:
        raise UsageError(f"--rows must be >= 2, got {args.rows}")
    out = prepare_out_dir(args.out)
    run = run_shape(args.shape, args.seed, grid=200, criteria=("predictive", "paper"), keep_history=True)
    history = run.history
    n = run.n_points
    print(f"Adaptive eye model on the {args.shape} eye, paper spiral ({n} A-scans, 20 um noise), predictive criteria")
    print(f"{'spiral':>7} {'points':>6} {'kind':>9} {'scan range':>10} {'sphere r':>8} {'ellipsoid radii (mm)':>24} {'SF MAE':>8} {'EF MAE':>8}")
    for k in np.linspace(0, len(run.fractions) - 1, args.rows).round().astype(int):
        received = int(round(run.fractions[k] * n))
        u = next(h for h in reversed(history) if h.n_received <= received)
        radii = " ".join(f"{r:6.3f}" for r in sorted(u.ellipsoid_radii, reverse=True))
        print(f"{100 * run.fractions[k]:6.1f}% {u.n_points:6d} {u.kind:>9} {u.scan_range_mm:8.2f}mm {u.sphere_radius:8.3f} "
              f"{radii:>24} {1e3 * run.sf_mae_curve[k]:6.1f}um {1e3 * run.ef_mae_curve[k]:6.1f}um")
    t = run.transitions["predictive"]
    summary = {
        "shape": args.shape,
        "n_points": n,
        "kind_final": history[-1].kind,
        "transition_at": t,
        "optimal_transition_at": run.optimal_transition_at,
        "paper_criteria_transition_at": run.transitions["paper"],
        "ef_mae_mm": [run.ef.mae.mean, run.ef.mae.sd],
        "sf_mae_mm": [run.sf.mae.mean, run.sf.mae.sd],
        "mmae_mm": [run.ef.mmae.mean, run.ef.mmae.sd],
        "ellipsoid_radii_mm": sorted(map(float, history[-1].ellipsoid_radii), reverse=True),
    }
    write_json(out / "demo.json", summary)
    save_figure(
        fig5(args.shape, run.fractions, run.sf_mae_curve, run.ef_mae_curve, run.criteria_met_at["paper"], t,
             run.optimal_transition_at, "predictive", 1),
        out / "demo_mae.png",
    )
    print(f"\nswitched to the ellipsoid at {100 * t:.1f} % of the spiral (optimal {100 * (run.optimal_transition_at or 0):.1f} %); "
          f"final EF MAE {1e3 * run.ef.mae.mean:.1f} um (exact, 200 x 200 truth sampling)" if t is not None else "\nstayed a sphere")
    print(f"wrote {out / 'demo.json'} and {out / 'demo_mae.png'}")
    return 0
