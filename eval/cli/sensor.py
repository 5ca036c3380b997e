"""`vitreoguard sensor`: the spiral scan through the robot and the simulated iiOCT, the
whole chain A-scan -> distance -> point (reported joints, calibrated sensor pose) ->
adaptive model, on one eye shape.

Writes sensor.json (distance bias and SD against the true distance, the
invalid fraction, the outliers the model's gate rejected, the final EF and SF MAE in the
exact form against the true retina, the final kind) and ascans.png (example A-scans at
normal and oblique incidence and with a floater: raw, reference response, detected and
true retina).
"""
from __future__ import annotations

import numpy as np

from eval.cli.args import SEED, add_eye_param, choice, eye_params, number, out_dir
from eval.cli.io import prepare_out_dir, save_figure, write_json
from eval.cli.loop_flags import add_model_flag, local_model
from eval.experiments.boundary import SPIRAL_RADIUS_MM, SPIRAL_REVOLUTIONS, SPIRAL_SPEED_MM_S, spiral_pitch_mm
from models.eyes import EYE_SHAPES

OUTLIERS = number(0.0, 0.5, "(fraction)")
SPEED = number(1.0, 17.0, "mm/s")
REVOLUTIONS = number(1.0, 18.0, "revolutions")


def register(sub) -> None:
    p = sub.add_parser("sensor", help="spiral scan through robot + iiOCT + model: sensor.json, ascans.png")
    p.add_argument("--out", type=out_dir, required=True, help="output directory")
    p.add_argument("--shape", type=choice("shape", EYE_SHAPES), default="emmetropic",
                   help=f"true eye: one of {' '.join(EYE_SHAPES)}")
    add_eye_param(p)
    p.add_argument("--seed", type=SEED, default=0, help=f"speckle, noise and floater seed, {SEED.range}")
    p.add_argument("--mode", choices=("ascan", "distance"), default="ascan",
                   help="full A-scans or the extractor's error model")
    p.add_argument("--outliers", type=OUTLIERS, default=0.0,
                   help=f"fraction of samples with a floater on the beam, {OUTLIERS.range}")
    p.add_argument("--speed-mm-s", type=SPEED, default=SPIRAL_SPEED_MM_S, help=f"tip speed along the spiral, {SPEED.range}")
    p.add_argument("--revolutions", type=REVOLUTIONS, default=SPIRAL_REVOLUTIONS,
                   help=f"spiral revolutions over its {SPIRAL_RADIUS_MM:g} mm radius, {REVOLUTIONS.range}")
    add_model_flag(p)
    p.set_defaults(func=main)


def run_sensor(args) -> dict:
    """The chain on args.shape; sensor.json's content."""
    from eval.experiments.boundary import build_model_by_spiral
    from eval.experiments.model_report import model_summary, update_timing
    from eval.closed_loop import LoopConfig
    from eval.cli.boundary import make_loop
    from planning import SurgeryScenario

    scenario = SurgeryScenario(eye_name=args.shape, eye_params=args.eye_params)
    config = LoopConfig(sensor_mode=args.mode, local_model=local_model(args))
    loop = make_loop(scenario, config, sensor_seed=args.seed, floater_rate=args.outliers)
    build = build_model_by_spiral(loop, args.speed_mm_s, pitch_mm=spiral_pitch_mm(args.revolutions), revolutions=args.revolutions,
                                  progress=f"spiral scan ({args.shape} eye, {args.mode} mode)")
    ms = loop.model
    err = np.array(ms.errors_mm)
    clean = err[np.abs(err) < 0.2] if args.outliers > 0 else err  # bias/SD of the extractor, not of the floaters
    return {
        "distance_bias_um": 1e3 * float(np.median(clean)),
        "distance_sd_um": 1e3 * float(1.4826 * np.median(np.abs(clean - np.median(clean)))),
        "invalid_fraction": ms.n_invalid / ms.n_samples,
        "outliers_rejected": int(build.model.n_rejected_outliers),
        "ef_mae_um": build.ef_mae_um,
        "sf_mae_um": build.sf_mae_um,
        "kind_final": build.kind_final,
        "shape": args.shape, "eye_params": args.eye_params, "mode": args.mode, "seed": args.seed, "floater_rate": args.outliers,
        "n_samples": ms.n_samples, "n_points": build.model.n_points,
        "distance_error_p99_um": 1e3 * float(np.percentile(np.abs(err), 99)),
        "calibration_error": {"sensor_offset_S_mm": scenario.sensor_offset_S_mm.tolist(),
                              "sensor_rotvec_S_rad": scenario.sensor_rotvec_S_rad.tolist()},
        "scan_s": build.run.duration_s, "wall_s": build.run.wall_s,
        "model": model_summary(loop, build), "model_update_us_per_ascan": update_timing(loop),
    }


def main(args) -> int:
    args.eye_params = eye_params(args.eye_param, args.shape)
    out = prepare_out_dir(args.out)
    result = run_sensor(args)
    save_figure(ascans_figure(args.seed), out / "ascans.png")
    write_json(out / "sensor.json", result)
    for key in ("distance_bias_um", "distance_sd_um", "invalid_fraction", "outliers_rejected", "ef_mae_um",
                "sf_mae_um", "kind_final"):
        v = result[key]
        print(f"{key:20s} {v:.4g}" if isinstance(v, float) else f"{key:20s} {v}")
    print(f"wrote {out / 'sensor.json'} and {out / 'ascans.png'}")
    return 0


def ascans_figure(seed: int):
    """Example A-scans: 8 mm at normal incidence, 8 mm at 45 deg, and 8 mm with a floater
    at 4 mm; each with the detected and the true retina and the retina's reference
    response (the mean of 32 synthetic scans at the detected distance: speckle and
    noise averaged out)."""
    import matplotlib.pyplot as plt

    from models.iioct import DistanceExtractor, Floater, OctEngine, synthesize_ascan

    engine = OctEngine()
    extractor = DistanceExtractor(engine)
    rng = np.random.default_rng(seed)
    cases = (("normal incidence", 8.0, 0.0, ()), ("45 deg incidence", 8.0, np.radians(45.0), ()),
             ("floater at 4 mm", 8.0, 0.0, (Floater(4.0, 35.0),)))
    fig, axes = plt.subplots(len(cases), 1, figsize=(10, 8), sharex=True)
    for ax, (title, d, a, floaters) in zip(axes, cases):
        scan = synthesize_ascan(d, a, rng, engine=engine, floaters=floaters)
        m = extractor(scan)
        # geometric distance from the fiber tip: the tip reflection sits at tip_offset_mm of optical path
        depth = (np.arange(engine.n_samples) * engine.sample_spacing_mm - engine.tip_offset_mm) / engine.group_index
        ax.plot(depth, scan, lw=0.5, color="0.3", label="A-scan")
        if m.valid:
            ref = np.mean([synthesize_ascan(m.distance_mm, a, rng, engine=engine) for _ in range(32)], axis=0)
            ax.plot(depth, ref, lw=0.8, color="tab:orange", label="reference response at the detected distance")
        ax.axvline(d, color="tab:green", ls="--", lw=1, label="true retina")
        if m.valid:
            ax.axvline(m.distance_mm, color="tab:red", ls=":", lw=1.2,
                       label=f"detected ({1e3 * (m.distance_mm - d):+.0f} um, NCC {m.confidence:.2f})")
        ax.set_title(f"{title}: " + ("valid" if m.valid else f"invalid ({m.reason})"), fontsize=9)
        ax.set_xlim(-0.5, d + 3.0)
        ax.set_ylabel("amplitude (noise RMS)")
        ax.legend(fontsize=7, loc="upper right")
    axes[-1].set_xlabel("distance from the fiber tip along the beam (mm, geometric: optical path / group index)")
    fig.tight_layout()
    return fig
