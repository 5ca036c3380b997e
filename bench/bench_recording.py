"""Recording figures (the targets of record/fit): the time offset on the six shapes, the
registration to a printed phantom, record -> fit against the closed loop, and the fit's
speed on a 2-minute recording.

    python -m bench bench_recording            # everything (about an hour on 2 busy cores)
    python bench/bench_recording.py offset     # one part: offset | registration | mae | speed

Each recording is simulated (eval.recording.simulate, encoder noise 20 urad, the
scenario's default sensor calibration error) into a temporary bag and fitted as
`vitreoguard fit` does. Prints one line per case and the JSON of all figures at the end.
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path


if __name__ == "__main__":
    sys.path.insert(0, os.getcwd())

from eval.recording.fit import fit_recording, read_recording
from eval.recording.ground_truth import placed_mae_um, placement_error, register_fit
from eval.recording.simulate import RecordingSpec, write_recording
from models.calibration.plate import SensorPose
from models.eyes import EYE_SHAPES, make_eye
from models.eyes.mesh import lower_half_shell

OFFSETS_MS = (-10.0, -4.3, 0.0, 3.7, 10.0)


def _record_and_fit(spec: RecordingSpec, sensor=None):
    """(truth, FitResult, wall s of read+fit, CPU s of read+fit, recording duration s)."""
    with tempfile.TemporaryDirectory(dir=os.environ.get("VITREOGUARD_BENCH_TMP")) as tmp:
        truth = write_recording(Path(tmp) / "bag", spec)
        w0, c0 = time.perf_counter(), time.process_time()
        joints, oct = read_recording(Path(tmp) / "bag")
        result = fit_recording(joints, oct, sensor)
        return truth, result, time.perf_counter() - w0, time.process_time() - c0, truth["duration_s"]


def offsets() -> dict:
    """Offset error (ms) per shape and offset; short scans (the synchronisation is the same)."""
    out = {}
    for shape in EYE_SHAPES:
        for k, off in enumerate(OFFSETS_MS):
            spec = RecordingSpec(shape=shape, time_offset_s=1e-3 * off, seed=k, revolutions=1.0, pitch_mm=9.0)
            _, r, *_ = _record_and_fit(spec)
            err = 1e3 * r.offset.offset_s - off
            out[f"{shape} {off:+g} ms"] = err
            print(f"  offset {shape:10s} {off:+6.1f} ms: estimate {1e3 * r.offset.offset_s:+8.3f} ms, error {err:+.3f} ms, "
                  f"gain {r.offset.gain:+.3f}, residual {1e3 * r.offset.residual_rms_mm:.1f} um", flush=True)
    worst = max(abs(v) for v in out.values())
    print(f"  offset: worst |error| {worst:.3f} ms over {len(out)} recordings (target 0.5 ms)")
    return {"errors_ms": out, "worst_abs_error_ms": worst}


def _true_sensor(truth) -> SensorPose:
    s = truth["sensor"]["true"]
    return SensorPose(s["p_FS_mm"], s["u_F"])


def registration(shapes=("staphyloma", "detached", "emmetropic")) -> dict:
    """The registered placement against the recording's truth, with the nominal sensor
    pose (the default calibration error left in the points) and with the true one."""
    out = {}
    for shape in shapes:
        spec = RecordingSpec(shape=shape, time_offset_s=0.0042, seed=7)
        truth, r, *_ = _record_and_fit(spec)
        mesh = lower_half_shell(make_eye(shape))
        for label, sensor in (("nominal", None), ("true", _true_sensor(truth))):
            res = r if sensor is None else fit_recording(r.joints, r.oct, sensor)
            reg = register_fit(res.accepted, res.model.shape, *mesh)
            err = placement_error(reg, truth["R_WE"], truth["p_WE_mm"])
            out[f"{shape} {label} sensor pose"] = {**err, "registration_rmse_um": reg["registration_rmse_um"],
                                                   "mae_um": reg["mae_um"]}
            print(f"  registration {shape:10s} ({label:7s} sensor pose): position {err['position_error_um']:7.1f} um, "
                  f"rotation {err['rotation_error_deg']:7.3f} deg, rmse {reg['registration_rmse_um']:.1f} um "
                  f"(target 20 um, 0.05 deg)", flush=True)
    return out


def _closed_loop_model(shape: str):
    """The closed loop's spiral-built model on `shape` (A-scan mode, the same spiral)."""
    from eval.closed_loop import ClosedLoop, LoopConfig
    from eval.experiments.boundary import build_model_by_spiral
    from planning import SurgeryScenario

    scenario = SurgeryScenario(eye_name=shape)
    loop = ClosedLoop(scenario, LoopConfig(sensor_mode="ascan"), sensor_seed=0)
    build = build_model_by_spiral(loop, 15.0, pitch_mm=1.5, revolutions=6.0)
    return scenario, build


def mae(shapes=("emmetropic", "myopic", "hyperopic")) -> dict:
    """record -> fit (STL ground truth) against the closed loop on the same eye."""
    out = {}
    for shape in shapes:
        truth, r, *_ = _record_and_fit(RecordingSpec(shape=shape, time_offset_s=0.0063, seed=3))
        mesh = lower_half_shell(make_eye(shape))
        reg = register_fit(r.accepted, r.model.shape, *mesh)
        rec_true = placed_mae_um(*mesh, r.model.shape, truth["R_WE"], truth["p_WE_mm"])
        scenario, build = _closed_loop_model(shape)
        loop_true = placed_mae_um(*mesh, build.model.shape, truth["R_WE"], truth["p_WE_mm"])
        out[shape] = {"recording_mae_um": reg["mae_um"], "recording_mae_true_placement_um": rec_true,
                      "closed_loop_mae_true_placement_um": loop_true, "closed_loop_ef_mae_um": build.ef_mae_um,
                      "recording_kind": r.model.kind, "closed_loop_kind": build.model.kind,
                      "ratio": reg["mae_um"] / loop_true}
        print(f"  mae {shape:10s}: recording {reg['mae_um']:.1f} um after registration ({rec_true:.1f} um at the true "
              f"placement), closed loop {loop_true:.1f} um on the same mesh ({build.ef_mae_um:.1f} um its ef_mae_um); "
              f"ratio {reg['mae_um'] / loop_true:.2f} (target within 20 %)", flush=True)
    return out


def speed() -> dict:
    """fit on a 2-minute recording (the paper's 18-turn spiral at 4.3 mm/s)."""
    spec = RecordingSpec(shape="myopic", time_offset_s=0.002, revolutions=18.0, pitch_mm=0.5, speed_mm_s=4.3)
    _, r, wall, cpu, duration = _record_and_fit(spec)
    print(f"  speed: a {duration:.1f} s recording ({len(r.oct.t_s)} A-scans) read, extracted and fitted in {wall:.1f} s "
          f"wall ({cpu:.1f} s CPU) (target: less than its duration)", flush=True)
    return {"recording_s": duration, "fit_wall_s": wall, "fit_cpu_s": cpu, "n_ascans": int(len(r.oct.t_s))}


PARTS = {"offset": offsets, "registration": registration, "mae": mae, "speed": speed}


def run(parts=tuple(PARTS)) -> dict:
    out = {name: PARTS[name]() for name in parts}
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    run(tuple(sys.argv[1:]) or tuple(PARTS))
