"""`vitreoguard fit`: fit a recording (a ROS 2 bag or a CSV pair, eval.recording.bag):
extract every A-scan's distance, estimate the OCT-robot time offset from the
synchronisation segment, rebuild the retinal points with the calibrated sensor pose, run
the adaptive model (eval.recording.fit); with --ground-truth, register the points (the
extractor's bias taken out of them, unless --no-bias-removal) to the phantom's STL and
measure the model there (eval.recording.ground_truth).

fit.json: `time_offset_ms` (OCT clock minus robot clock, positive when the OCT stream
lags), `kind`, `n_points`, `sf_fmae_um`, `ef_fmae_um`, `lf_fmae_um` (the local-global
model's), `sync`, the model; with a ground truth `mae_um`, `lf_mae_um`,
`registration_rmse_um` and `registration`. Plots: sync.png, fit.png.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

from eval.cli.args import number, out_dir
from eval.cli.io import UsageError, prepare_out_dir, save_figure, write_json
from eval.cli.progress import phase, progress_bar
from eval.cli.workers import add_worker_flags

MAX_OFFSET_MS = number(1.0, 1000.0, "ms")
ICP_DISTANCE = number(0.01, 5.0, "mm")


def register(sub) -> None:
    p = sub.add_parser("fit", help="fit a recording (ROS 2 bag or CSV pair): fit.json, sync.png, fit.png")
    p.add_argument("--recording", required=True,
                   help="a ROS 2 bag (folder, .mcap or .db3) with JointState and A-scan Image topics, or a CSV-pair folder")
    p.add_argument("--out", type=out_dir, required=True, help="output directory")
    p.add_argument("--calibration", default=None,
                   help="the sensor pose: a `vitreoguard calibrate` calibration.json or {p_FS_mm, u_F} (default: nominal)")
    p.add_argument("--ground-truth", default=None, metavar="MESH.stl",
                   help="the phantom's watertight STL in mm (eye frame): register the fit to it, report mae_um")
    p.add_argument("--joint-topic", default=None, help="the JointState topic (default: the bag's only one)")
    p.add_argument("--ascan-topic", default=None, help="the A-scan Image topic (default: the bag's only one)")
    p.add_argument("--max-offset-ms", type=MAX_OFFSET_MS, default=100.0,
                   help=f"time offsets searched, +-{MAX_OFFSET_MS.range}")
    p.add_argument("--icp-max-distance-mm", type=ICP_DISTANCE, default=1.0,
                   help=f"ICP's maximum correspondence distance, {ICP_DISTANCE.range} (paper: 0.1-1.0)")
    p.add_argument("--icp-sweep", action="store_true",
                   help="also register with every correspondence distance 0.1, 0.2, ..., 1.0 mm (the paper's sweep)")
    p.add_argument("--no-bias-removal", action="store_true",
                   help="register the points as extracted, without taking out the extractor's bias tabulated on the "
                        "project's simulated OCT engine (for an engine unlike it)")
    add_worker_flags(p, ray=False)
    p.set_defaults(func=main)


def _check_writable(out: Path) -> None:
    """UsageError when `out` cannot be made a writable folder (checked before any work, creating nothing)."""
    probe = out
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise UsageError(f"output directory {out} is not writable")


def run_fit(args) -> tuple[dict, object]:
    """(fit.json's content, the FitResult) of validated args; RecordingError / SyncError on bad input."""
    from eval.recording.fit import fit_recording, read_calibration, read_recording
    from eval.recording.ground_truth import load_stl, register_recording

    sensor = read_calibration(args.calibration) if args.calibration is not None else None
    mesh = load_stl(args.ground_truth) if args.ground_truth is not None else None
    t0 = time.perf_counter()
    bar = []

    def progress(n: int, total: int) -> None:
        if not bar:
            bar.append(progress_bar(total, f"reading the recording, extracting A-scans ({args.jobs} processes)",
                                    unit="A-scan"))
        bar[0].update(n - bar[0].n)

    try:
        joints, oct = read_recording(args.recording, joint_topic=args.joint_topic, ascan_topic=args.ascan_topic,
                                     progress=progress, jobs=args.jobs)
    finally:
        if bar:
            bar[0].close()
    t_read = time.perf_counter() - t0
    with phase("synchronising the streams and fitting the model"):
        result = fit_recording(joints, oct, sensor, 1e-3 * args.max_offset_ms)
    out = {**result.summary(), "recording": str(args.recording)}
    if mesh is not None:
        if result.model.shape is None:
            raise UsageError("--ground-truth: the recording gave no model to register")
        with phase("registering the points to the ground-truth mesh (ICP)"):
            reg = register_recording(result, *mesh, args.icp_max_distance_mm, args.icp_sweep, not args.no_bias_removal)
        out.update({"mae_um": reg["mae_um"], "lf_mae_um": reg["lf_mae_um"],
                    "registration_rmse_um": reg["registration_rmse_um"], "registration": reg,
                    "ground_truth": str(args.ground_truth)})
    out["recording_duration_s"] = float(oct.t_s[-1] - oct.t_s[0])
    out["wall_s"] = {"read_and_extract": t_read, "total": time.perf_counter() - t0}
    return out, result


def main(args) -> int:
    from eval.recording.bag import RecordingError
    from planning.clock_sync import SyncError
    from eval.recording.plots import figure_fit, figure_sync

    out_dir = Path(args.out)
    _check_writable(out_dir)
    try:
        out, result = run_fit(args)
    except (RecordingError, SyncError) as exc:  # bad input: one line
        raise UsageError(str(exc)) from None
    out_dir = prepare_out_dir(out_dir)
    save_figure(figure_sync(result), out_dir / "sync.png")
    save_figure(figure_fit(result), out_dir / "fit.png")
    write_json(out_dir / "fit.json", out)
    for key in ("time_offset_ms", "kind", "n_points", "sf_fmae_um", "ef_fmae_um", "lf_fmae_um", "mae_um", "lf_mae_um",
                "registration_rmse_um"):
        if key in out:
            v = out[key]
            print(f"{key:22s} {v:.4g}" if isinstance(v, float) else f"{key:22s} {v}")
    print(f"wrote {out_dir / 'fit.json'}, {out_dir / 'sync.png'} and {out_dir / 'fit.png'}")
    return 0
