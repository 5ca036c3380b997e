"""`vitreoguard record`: a simulated rig recording (eval.recording.simulate): a ROS 2 bag
(MCAP storage) in OUT/recording with the robot's JointState at the joint rate on the
robot's clock and the iiOCT A-scans (one-row mono16 Image) at 2 kHz on the OCT's clock,
offset by --time-offset-ms; the synchronisation motion first, then the spiral: through
the trocar of the eye in surgery (--scan surgery, the default), or over the printed lower
half open on the bench, seen from above (--scan phantom, planning.phantom). The run's
ground truth (the eye and its placement, the sensor's calibration error, the offset)
goes to OUT/truth.json, never into the bag."""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from eval.cli.args import SEED, add_eye_param, choice, eye_params, number, out_dir
from eval.cli.io import UsageError, prepare_out_dir, write_json
from eval.cli.progress import progress_bar
from eval.recording import SCANS
from models.eyes import EYE_SHAPES

OFFSET_MS = number(-100.0, 100.0, "ms")
REVOLUTIONS = number(0.5, 18.0, "revolutions")
SPEED = number(1.0, 17.0, "mm/s")
SYNC_S = number(1.0, 10.0, "s")
ENCODER_URAD = number(0.0, 1000.0, "urad")
JOINT_RATE = number(50.0, 1000.0, "Hz")
BAG_NAME = "recording"


def register(sub) -> None:
    p = sub.add_parser("record", help="simulated rig recording: a ROS 2 bag (MCAP) and truth.json")
    p.add_argument("--out", type=out_dir, required=True, help="output directory (the bag goes to OUT/recording)")
    p.add_argument("--shape", type=choice("shape", EYE_SHAPES), default="emmetropic",
                   help=f"true eye: one of {' '.join(EYE_SHAPES)}")
    add_eye_param(p)
    p.add_argument("--scan", type=choice("scan", SCANS), default="surgery",
                   help="surgery: the eye in the head, the spiral through the trocar; phantom: the eye's printed lower "
                        "half open on the bench, the spiral above it (the whole half seen from above)")
    p.add_argument("--time-offset-ms", type=OFFSET_MS, default=0.0,
                   help=f"OCT clock minus robot clock (positive: the OCT stream lags), {OFFSET_MS.range}")
    p.add_argument("--seed", type=SEED, default=0, help=f"speckle, noise and encoder-noise seed, {SEED.range}")
    p.add_argument("--revolutions", type=REVOLUTIONS, default=6.0,
                   help=f"spiral revolutions over its 9 mm radius, {REVOLUTIONS.range}")
    p.add_argument("--speed-mm-s", type=SPEED, default=15.0, help=f"tip speed along the spiral, {SPEED.range}")
    p.add_argument("--sync-s", type=SYNC_S, default=3.0, help=f"duration of the synchronisation motion, {SYNC_S.range}")
    p.add_argument("--encoder-noise-urad", type=ENCODER_URAD, default=20.0,
                   help=f"SD of the noise on each reported joint angle, {ENCODER_URAD.range}")
    p.add_argument("--joint-rate-hz", type=JOINT_RATE, default=1000.0,
                   help=f"the robot's JointState rate, {JOINT_RATE.range}")
    p.set_defaults(func=main)


def spec_of(args):
    """The RecordingSpec of validated args."""
    from eval.recording.simulate import RecordingSpec

    return RecordingSpec(shape=args.shape, eye_params=args.eye_params, scan=args.scan, time_offset_s=1e-3 * args.time_offset_ms,
                         seed=args.seed, encoder_noise_rad=1e-6 * args.encoder_noise_urad,
                         joint_rate_hz=args.joint_rate_hz, pitch_mm=9.0 / args.revolutions,
                         revolutions=args.revolutions, speed_mm_s=args.speed_mm_s, sync_s=args.sync_s)


def main(args) -> int:
    args.eye_params = eye_params(args.eye_param, args.shape)
    out = Path(args.out)
    if (out / BAG_NAME).exists():
        raise UsageError(f"--out {out} already holds {BAG_NAME}/: choose another folder or remove it")
    out = prepare_out_dir(out)
    from eval.recording.simulate import write_recording

    spec = spec_of(args)
    tmp = Path(tempfile.mkdtemp(dir=out, prefix=".recording-"))
    try:
        bar = progress_bar(1000, f"recording ({args.shape} eye, {args.scan})", unit="permille")
        with bar:
            def progress(done_s, total_s):
                bar.update(int(1000 * done_s / total_s) - bar.n)

            truth = write_recording(tmp / BAG_NAME, spec, progress=progress)
        os.replace(tmp / BAG_NAME, out / BAG_NAME)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    write_json(out / "truth.json", truth)
    print(f"recorded {truth['duration_s']:.2f} s: {truth['n_joint_states']} joint states, {truth['n_ascans']} A-scans, "
          f"time offset {truth['time_offset_ms']:+.3f} ms")
    print(f"wrote {out / BAG_NAME} (ROS 2 bag, MCAP) and {out / 'truth.json'}")
    return 0
