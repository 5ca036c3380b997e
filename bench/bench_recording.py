"""Recording figures (the targets of record/fit): the time offset on the six shapes, the
registration to a printed phantom, record -> fit against the same scan without the
recording round trip, and the fit's speed on a 2-minute recording.

    python -m bench bench_recording            # the short set (about 5 min on 2 idle cores)
    python bench/bench_recording.py all        # every case (about 40 min): the README's figures
    python bench/bench_recording.py offset     # one part: offset | phantom | registration | mae | phantom_scan | speed

Each recording is simulated (eval.recording.simulate, encoder noise 20 urad, the
scenario's default sensor calibration error) into a temporary bag and fitted as
`vitreoguard fit` does (with every core for the extraction). Prints one line per case
and the JSON of all figures at the end. The short set: the offset at -10 and +10 ms on
each shape, the phantom registration, registration and MAE on the emmetropic eye;
`all` adds -4.3, 0 and +3.7 ms, the staphyloma and detached recordings, the myopic and
hyperopic eyes, the true sensor pose and the 2-minute recording.
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

import numpy as np
from scipy.spatial.transform import Rotation

from eval.experiments.campaign import default_jobs
from eval.recording.bag import RecordingError
from eval.recording.fit import fit_recording, read_recording
from eval.recording.ground_truth import mesh_symmetries, placed_mae_um, placement_error, register_fit, register_recording
from eval.recording.simulate import RecordingSpec, direct_model, write_recording
from models import fit_sphere
from models.calibration.plate import SensorPose
from models.eyes import EYE_SHAPES, make_eye
from models.eyes.mesh import lower_half_shell
from models.shapes.sampling import unit_sphere_grid

FULL = {"all"} & set(sys.argv[1:]) != set()
OFFSETS_MS = (-10.0, -4.3, 0.0, 3.7, 10.0) if FULL else (-10.0, 10.0)


def _record_and_fit(spec: RecordingSpec, sensor=None):
    """(truth, FitResult, wall s of read+fit, CPU s of this process's read+fit, recording duration s)."""
    with tempfile.TemporaryDirectory(dir=os.environ.get("VITREOGUARD_BENCH_TMP")) as tmp:
        truth = write_recording(Path(tmp) / "bag", spec)
        w0, c0 = time.perf_counter(), time.process_time()
        joints, oct = read_recording(Path(tmp) / "bag", jobs=default_jobs())
        result = fit_recording(joints, oct, sensor)
        return truth, result, time.perf_counter() - w0, time.process_time() - c0, truth["duration_s"]


def offsets() -> dict:
    """Offset error (ms) per shape and offset; short scans (the synchronisation is the same)."""
    out = {}
    for shape in EYE_SHAPES:
        for k, off in enumerate(OFFSETS_MS):
            spec = RecordingSpec(shape=shape, time_offset_s=1e-3 * off, seed=k, revolutions=0.5, pitch_mm=18.0)
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


def _placement(points, shape: str, R_WE, p_WE, model=None) -> tuple[dict, dict]:
    """(register_fit's dict, placement_error's dict modulo the mesh's symmetries) of a
    FitResult (register_recording) or of points (N, 3) mm with a `model`."""
    mesh = lower_half_shell(make_eye(shape))
    reg = register_fit(points, model, *mesh) if model is not None else register_recording(points, *mesh)
    return reg, placement_error(reg, R_WE, p_WE, symmetries=mesh_symmetries(*mesh))


def _print_placement(label: str, err: dict, rmse_um: float) -> None:
    about = ", ".join(f"{a:.3f} (SD {s:.3f})" for a, s in zip(err["rotation_error_about_axes_deg"], err["rotation_sd_deg"]))
    print(f"  {label}: position {err['position_error_um']:6.1f} um, rotation {err['rotation_error_deg']:.3f} deg "
          f"(about its principal axes: {about} deg; {err['defined_axes']} defined: {err['rotation_error_defined_deg']:.3f} "
          f"deg), rmse {rmse_um:.1f} um (target 20 um, 0.05 deg)", flush=True)


def phantom(n: int = 40000, noise_mm: float = 0.012) -> dict:
    """The registration alone, on a phantom scanned over its lower half (80 deg about the
    pole, as a phantom on the bench allows): n points with the extractor's noise, at a
    placement tilted 37 deg (tests/eval/test_registration.py asserts the same)."""
    out = {}
    R_WE = Rotation.from_rotvec(np.radians(37.0) * np.array([0.48, -0.6, 0.64])).as_matrix()
    p_WE = np.array([141.3, -52.7, 33.9])
    U = unit_sphere_grid(400, 800)
    U = U[np.degrees(np.arccos(np.clip(-U[:, 2], -1.0, 1.0))) < 80.0]
    for k, shape in enumerate(EYE_SHAPES):
        rng = np.random.default_rng(k + 40)
        V = U[rng.choice(len(U), n, replace=False)]
        P_W = (make_eye(shape).surface_points(V) + noise_mm * rng.standard_normal(n)[:, None] * V) @ R_WE.T + p_WE
        reg, err = _placement(P_W, shape, R_WE, p_WE, fit_sphere(P_W))
        out[shape] = {**err, "registration_rmse_um": reg["registration_rmse_um"]}
        _print_placement(f"phantom {shape:10s}", err, reg["registration_rmse_um"])
    return out


def registration(shapes=("staphyloma", "detached", "emmetropic") if FULL else ("emmetropic",)) -> dict:
    """The registered placement against the recording's truth (the 6-turn spiral through
    the trocar), with the nominal sensor pose (the default calibration error left in the
    points) and, with `all`, with the true one."""
    out = {}
    for shape in shapes:
        spec = RecordingSpec(shape=shape, time_offset_s=0.0042, seed=7)
        truth, r, *_ = _record_and_fit(spec)
        for label, sensor in (("nominal", None), ("true", _true_sensor(truth)))[:2 if FULL else 1]:
            res = r if sensor is None else fit_recording(r.joints, r.oct, sensor)
            reg, err = _placement(res, shape, truth["R_WE"], truth["p_WE_mm"])
            out[f"{shape} {label} sensor pose"] = {**err, "registration_rmse_um": reg["registration_rmse_um"],
                                                   "mae_um": reg["mae_um"]}
            _print_placement(f"registration {shape:10s} ({label:7s} sensor pose)", err, reg["registration_rmse_um"])
    return out


def _against_reference(spec, truth, res, reg, mesh, true_pose: bool) -> dict:
    """The recording's mae_um (after registration and at the true placement) against the
    same scan without the round trip (eval.recording.simulate.direct_model), um."""
    rec_true = placed_mae_um(*mesh, res.model.shape, truth["R_WE"], truth["p_WE_mm"])
    ref = direct_model(spec, true_sensor_pose=true_pose)
    ref_mae = placed_mae_um(*mesh, ref.shape, truth["R_WE"], truth["p_WE_mm"])
    return {"recording_mae_um": reg["mae_um"], "recording_lf_mae_um": reg["lf_mae_um"],
            "recording_mae_true_placement_um": rec_true, "reference_mae_um": ref_mae,
            "recording_kind": res.model.kind, "reference_kind": ref.kind, "ratio": reg["mae_um"] / ref_mae,
            "ratio_true_placement": rec_true / ref_mae}


def mae(shapes=("emmetropic", "myopic", "hyperopic") if FULL else ("emmetropic",)) -> dict:
    """record -> fit (STL ground truth) against the same scan without the round trip
    (eval.recording.simulate.direct_model: the loop's sensor and model on the same true
    motion, no bag, no offset estimate, no registration), nominal and (with `all`) true
    sensor pose in both."""
    out = {}
    for shape in shapes:
        spec = RecordingSpec(shape=shape, time_offset_s=0.0063, seed=3)
        truth, r, *_ = _record_and_fit(spec)
        mesh = lower_half_shell(make_eye(shape))
        for label, true_pose in (("nominal", False), ("true", True))[:2 if FULL else 1]:
            res = fit_recording(r.joints, r.oct, _true_sensor(truth)) if true_pose else r
            reg = register_recording(res, *mesh)
            m = _against_reference(spec, truth, res, reg, mesh, true_pose)
            rec_true, ref_mae = m["recording_mae_true_placement_um"], m["reference_mae_um"]
            out[f"{shape} {label} sensor pose"] = {**m, "lf_fmae_um": res.summary()["lf_fmae_um"]}
            print(f"  mae {shape:10s} ({label:7s} sensor pose): recording {reg['mae_um']:.1f} um after registration "
                  f"({rec_true:.1f} um at the true placement; local-global {reg['lf_mae_um']:.1f} um), the same scan "
                  f"without the round trip {ref_mae:.1f} um; ratio {reg['mae_um'] / ref_mae:.2f} "
                  f"({rec_true / ref_mae:.2f} at the true placement) (target within 20 %)", flush=True)
    return out


def phantom_scan(shapes=EYE_SHAPES if FULL else ("staphyloma",)) -> dict:
    """record --scan phantom -> fit with the STL: the printed lower half open on the bench,
    scanned from above (planning.phantom, the 6-turn spiral). The registered placement
    against the truth (modulo the mesh's symmetries, per principal axis) and mae_um
    against the same scan without the round trip (at the true placement), with the
    nominal sensor pose and, with `all`, the true one."""
    out = {}
    for k, shape in enumerate(shapes):
        spec = RecordingSpec(shape=shape, scan="phantom", time_offset_s=-0.0037, seed=20 + k)
        truth, r, *_ = _record_and_fit(spec)
        mesh = lower_half_shell(make_eye(shape))
        for label, true_pose in (("nominal", False), ("true", True))[:2 if FULL else 1]:
            res = fit_recording(r.joints, r.oct, _true_sensor(truth)) if true_pose else r
            try:
                reg = register_recording(res, *mesh)
            except RecordingError as exc:  # no start matches: reported, the other shapes go on
                out[f"{shape} {label} sensor pose"] = {"registration_failed": str(exc), "model": res.summary()["model"]}
                print(f"  phantom scan {shape:10s} ({label:7s} sensor pose): registration failed: {exc}", flush=True)
                continue
            err = placement_error(reg, truth["R_WE"], truth["p_WE_mm"], symmetries=mesh_symmetries(*mesh))
            m = _against_reference(spec, truth, res, reg, mesh, true_pose)
            rec_true, ref_mae = m["recording_mae_true_placement_um"], m["reference_mae_um"]
            out[f"{shape} {label} sensor pose"] = {
                **err, "registration_rmse_um": reg["registration_rmse_um"], "n_points": int(len(res.accepted)), **m,
                "sensor_error": reg["sensor_error"]}
            _print_placement(f"phantom scan {shape:10s} ({label:7s} sensor pose)", err, reg["registration_rmse_um"])
            if label == "nominal":
                s, true = reg["sensor_error"], truth["calibration_error"]
                print(f"    sensor error estimated: offset {1e3 * np.array(s['offset_S_mm'])} um, tilt "
                      f"{np.array(s['rotvec_S_deg'])} deg (true {1e3 * np.array(true['sensor_offset_S_mm'][:2])} um, "
                      f"{np.degrees(true['sensor_rotvec_S_rad'][:2])} deg)", flush=True)
            print(f"    mae: {reg['mae_um']:.1f} um after registration ({rec_true:.1f} um at the true placement; "
                  f"local-global {reg['lf_mae_um']:.1f} um; {res.model.kind}), the same scan without the round trip "
                  f"{ref_mae:.1f} um ({m['reference_kind']}); ratio {reg['mae_um'] / ref_mae:.2f} (target within 20 %)", flush=True)
    return out


def speed() -> dict:
    """fit on a 2-minute recording (the paper's 18-turn spiral at 4.3 mm/s)."""
    spec = RecordingSpec(shape="myopic", time_offset_s=0.002, revolutions=18.0, pitch_mm=0.5, speed_mm_s=4.3)
    _, r, wall, cpu, duration = _record_and_fit(spec)
    print(f"  speed: a {duration:.1f} s recording ({len(r.oct.t_s)} A-scans) read, extracted ({default_jobs()} processes) "
          f"and fitted in {wall:.1f} s wall ({cpu:.1f} s CPU in the main process) (target: less than its duration)",
          flush=True)
    return {"recording_s": duration, "fit_wall_s": wall, "fit_cpu_main_s": cpu, "n_ascans": int(len(r.oct.t_s)),
            "jobs": default_jobs()}


PARTS = {"offset": offsets, "phantom": phantom, "registration": registration, "mae": mae,
         "phantom_scan": phantom_scan, "speed": speed}
SHORT = ("offset", "phantom", "registration", "mae", "phantom_scan")


def run(parts=None) -> dict:
    parts = (tuple(PARTS) if FULL else SHORT) if not parts else parts
    out = {name: PARTS[name]() for name in parts}
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    run(tuple(a for a in sys.argv[1:] if a != "all"))
