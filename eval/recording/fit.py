"""The fit of a recording: A-scans -> distances -> time offset -> points -> adaptive model.

1. every A-scan through the project's extractor (models.iioct.DistanceExtractor), as it
   is read (eval.recording.bag), in worker processes (eval.recording.extraction);
2. the beam at each joint state: the robot's forward kinematics at the reported angles
   with the calibrated sensor pose (a `vitreoguard calibrate` calibration.json, or the
   nominal pose of the robot model);
3. the synchronisation segment in the robot's stream and the OCT-robot time offset
   (planning.clock_sync);
4. each valid A-scan after the segment: its point = beam origin + distance x direction at
   the robot time of its stamp minus the offset (joint angles interpolated linearly);
5. the adaptive model (sphere -> ellipsoid, the closed loop's criteria) updated with the
   points in stamp order, packets of 20 (the closed loop's 10 ms at 2 kHz);
6. the local-global model (models.local) of the whole recording: the local correction
   fitted at once to every point the model accepted, about the final global quadric
   (its centre and its Taylor expansion as the prior), every node solved and the
   correction used wherever it has data. An offline fit has all the points, so the
   online choice of when to use the correction (models.local.selection) does not apply;
   the batch costs about 6 us per point.

Units: mm, s, rad (ms, um where named).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eval.recording.bag import JointStream, OctStream, RecordingError, read_bag, read_csv_pair
from eval.recording.extraction import Extraction
from models import AdaptiveEyeModel
from models.adaptive.transition import PredictiveCriteria
from models.calibration.plate import SensorPose
from models.iioct import OctEngine
from models.metrics import fmae_exact
from planning.clock_sync import OffsetEstimate, estimate_time_offset, find_sync_segment

PACKET = 20
NOMINAL_TOLERANCE_MM = 20.0  # a calibrated sensor origin further than this from the nominal one is no calibration in mm


@dataclass(frozen=True)
class FitResult:
    """The fit of one recording: the streams, the synchronisation (segment indices into
    the joint stream, the beam's travel along itself there (mm), the offset estimate), the rebuilt points (N, 3) mm in W with their
    OCT stamps (N,) s, the model, the points it accepted (M, 3) mm, the sensor pose used,
    the local-global model, and the accepted points' beams (origins (M, 3) mm, unit
    directions (M, 3) in W) and how they move under the sensor's lateral calibration error
    (sensor_displacements)."""

    joints: JointStream
    oct: OctStream
    segment: tuple[int, int]
    sync_travel_mm: np.ndarray
    offset: OffsetEstimate
    t_points: np.ndarray
    points: np.ndarray
    model: AdaptiveEyeModel
    accepted: np.ndarray
    sensor: SensorPose
    calibrated: bool
    local: object = None  # models.local.field.LocalField (step 6), None without a global quadric
    accepted_beams: tuple = None
    accepted_displacements: np.ndarray = None  # (M, 3, 4): sensor_displacements of the accepted points

    def summary(self) -> dict:
        """fit.json's recording keys (module docstring of eval.cli.fit)."""
        m = self.model
        sf = fmae_exact(self.accepted, m.sphere).mean if m.sphere is not None else float("nan")
        ef = fmae_exact(self.accepted, m.ellipsoid).mean if m.ellipsoid is not None else float("nan")
        lf = fmae_exact(self.accepted, self.local).mean if self.local is not None else float("nan")
        i0, i1 = self.segment
        return {
            "time_offset_ms": 1e3 * self.offset.offset_s,
            "kind": m.kind,
            "n_points": int(m.n_points),
            "sf_fmae_um": _um(sf),
            "ef_fmae_um": _um(ef),
            "lf_fmae_um": _um(lf),
            "sync": {"segment_s": [float(self.joints.t_s[i0]), float(self.joints.t_s[i1 - 1])],
                     "gain": self.offset.gain, "residual_rms_um": 1e3 * self.offset.residual_rms_mm,
                     "n_samples": self.offset.n_samples},
            "n_ascans": int(len(self.oct.t_s)),
            "n_valid": int(np.isfinite(self.oct.distance_mm).sum()),
            "n_rebuilt": int(len(self.points)),
            "n_rejected_outliers": int(m.n_rejected_outliers),
            "model": _shape_dict(m.shape),
            "sensor_pose": {"p_FS_mm": self.sensor.p_FS.tolist(), "u_F": self.sensor.u_F.tolist(),
                            "source": "calibration" if self.calibrated else "nominal"},
        }


def _um(v: float):
    return None if not np.isfinite(v) else 1e3 * float(v)


def _shape_dict(shape) -> dict | None:
    if shape is None:
        return None
    if hasattr(shape, "radii"):
        return {"center_mm": shape.center.tolist(), "radii_mm": shape.radii.tolist(), "rotation": shape.rotation.tolist()}
    return {"center_mm": shape.center.tolist(), "radius_mm": float(shape.radius)}


def read_calibration(path) -> SensorPose:
    """The calibrated sensor pose from a `vitreoguard calibrate` calibration.json (its
    "recovered" pose) or a JSON {"p_FS_mm": [3], "u_F": [3]}; RecordingError on a file
    that is no such JSON, or whose origin is not in mm near the nominal one."""
    from eval.cli.calibrate import nominal_sensor

    try:
        data = json.loads(Path(path).read_text())
        pose = data.get("recovered", data)
        sensor = SensorPose(pose["p_FS_mm"], pose["u_F"])
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise RecordingError(f"--calibration {path}: not a calibration JSON with p_FS_mm (mm) and u_F (unit vector) "
                             f"({type(exc).__name__}: {exc})") from None
    off = float(np.linalg.norm(sensor.p_FS - nominal_sensor().p_FS))
    if off > NOMINAL_TOLERANCE_MM:
        raise RecordingError(f"--calibration {path}: p_FS_mm lies {off:.1f} mm from the nominal sensor origin (more than "
                             f"{NOMINAL_TOLERANCE_MM:g} mm): not in mm, or not this instrument")
    return sensor


def read_recording(path, engine: OctEngine = OctEngine(), joint_topic=None, ascan_topic=None,
                   progress=None, jobs: int = 1) -> tuple[JointStream, OctStream]:
    """The joint stream and the extracted OCT stream of a bag or a CSV-pair folder, both
    clocks' stamps counted from the first joint state's (s); the A-scans extracted in
    `jobs` processes (eval.recording.extraction). `progress(n, total)`: A-scans read so
    far of the bag's total (bags only)."""
    p = Path(path)
    if not p.exists():
        raise RecordingError(f"--recording {p} does not exist")
    if not os.access(p, os.R_OK | (os.X_OK if p.is_dir() else 0)):
        raise RecordingError(f"--recording {p} is not readable (permission denied)")
    extracted = True
    with Extraction(engine, jobs) as sink:
        if p.is_dir() and (p / "joints.csv").exists():
            joints, t_oct, d = read_csv_pair(p, sink, engine.n_samples)
            extracted = d is None
            d, conf = sink.result() if d is None else (d, np.ones(len(t_oct)))
        else:
            joints, t_oct = read_bag(p, sink, engine.full_scale, engine.n_samples, joint_topic, ascan_topic, progress)
            d, conf = sink.result()
    order = np.argsort(t_oct, kind="stable")
    t0 = joints.t_s[0]  # times from the first joint state: ROS stamps are ~1.7e9 s
    return JointStream(joints.t_s - t0, joints.q_rad), OctStream(t_oct[order] - t0, d[order], conf[order], extracted)


def beams_W(sensor: SensorPose, Q) -> tuple[np.ndarray, np.ndarray]:
    """(origins (M, 3) mm, unit directions (M, 3)) in W of the sensor pose `sensor` (flange
    frame) at the joint angles Q (M, 6) rad: the robot model's flange kinematics
    (planning.iioct.kernels.sensor_beams, compiled, vectorised)."""
    from planning.iioct.kernels import sensor_beams

    chain = _robot().chain
    R_F, p_F = chain.homes["F"]
    R_FS = sensor_frame(sensor.u_F)
    R_h, p_h = np.ascontiguousarray(R_F @ R_FS), R_F @ sensor.p_FS + p_F
    Q = np.ascontiguousarray(Q, dtype=float)
    return sensor_beams(chain.S, R_h, p_h, R_h, p_h, Q, Q)[2:]


def sensor_frame(u_F) -> np.ndarray:
    """R_FS (3, 3): the sensor frame S in the flange frame for the unit beam u_F (3,), z
    along the beam, x across it in the flange's x-z plane (or y-z, for a beam near y)."""
    z = np.asarray(u_F, dtype=float)
    x = np.cross([0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def sensor_displacements(sensor: SensorPose, Q, distances_mm) -> np.ndarray:
    """(M, 3, 4) mm per unit: how each point (the beam at joint angles Q (M, 6) rad,
    `distances_mm` (M,) along it) moves in W under the sensor pose's lateral calibration
    error xi = (offset along S's x and y (mm), rotation about S's x and y (rad)), the true
    sensor in the nominal frame S (sensor_frame): the registration estimates xi with the
    placement (eval.recording.ground_truth). The axial offset and the roll about the beam
    are left out: the first acts as a distance bias, the second moves no point."""
    R_FS = sensor_frame(sensor.u_F)
    X = beams_W(SensorPose(sensor.p_FS, R_FS[:, 0]), Q)[1]  # S's x and y axes in W
    Y = beams_W(SensorPose(sensor.p_FS, R_FS[:, 1]), Q)[1]
    d = np.asarray(distances_mm, dtype=float)[:, None]
    return np.stack([X, Y, -d * Y, d * X], axis=2)


_ROBOT = []


def _robot():
    """The robot model (no scenario: a recording's eye is unknown), built once."""
    if not _ROBOT:
        from planning import Robot

        _ROBOT.append(Robot())
    return _ROBOT[0]


def fit_recording(joints: JointStream, oct: OctStream, sensor: SensorPose | None = None,
                  max_offset_s: float = 0.1) -> FitResult:
    """Steps 2-5 of the module docstring on the streams; `sensor` None: the nominal pose.
    SyncError (a ValueError) when the synchronisation fails, RecordingError when no
    points remain."""
    from eval.cli.calibrate import nominal_sensor

    calibrated = sensor is not None
    sensor = nominal_sensor() if sensor is None else sensor
    if np.any(joints.q_rad < _robot().q_lower - 0.05) or np.any(joints.q_rad > _robot().q_upper + 0.05):
        raise RecordingError("joint positions leave the Meca500's joint limits: not this robot's angles in rad, or not "
                             "in the order J1..J6")
    O, U = beams_W(sensor, joints.q_rad)
    i0, i1 = find_sync_segment(O, U)
    s = (O[i0:i1] - O[i0]) @ U[i0]
    offset = estimate_time_offset(oct.t_s, oct.distance_mm, joints.t_s[i0:i1], s, max_offset_s)
    t_robot = oct.t_s - offset.offset_s
    use = np.isfinite(oct.distance_mm) & (t_robot > joints.t_s[i1 - 1]) & (t_robot <= joints.t_s[-1])
    if use.sum() < 10:
        raise RecordingError(f"only {int(use.sum())} valid A-scans follow the synchronisation segment: nothing to fit")
    Q = np.column_stack([np.interp(t_robot[use], joints.t_s, joints.q_rad[:, i]) for i in range(6)])
    O_p, U_p = beams_W(sensor, Q)
    P = O_p + oct.distance_mm[use, None] * U_p
    model = AdaptiveEyeModel(criteria=PredictiveCriteria())
    accepted = []
    row = {p.tobytes(): i for i, p in enumerate(P)}  # the model keeps points as given: each is a row of P
    for k in range(0, len(P), PACKET):
        if model.update(np.ascontiguousarray(P[k:k + PACKET]), np.ascontiguousarray(U_p[k:k + PACKET])) is not None:
            # the gate may add a point it held back from an earlier packet: looked up in all of P
            accepted.append([row[p.tobytes()] for p in model.last_accepted])
    acc = np.concatenate(accepted).astype(int) if accepted else np.zeros(0, dtype=int)
    return FitResult(joints, oct, (i0, i1), s, offset, oct.t_s[use], P, model, P[acc], sensor, calibrated,
                     local_fit(P[acc], model.shape, U_p[acc]), (O_p[acc], U_p[acc]),
                     sensor_displacements(sensor, Q[acc], oct.distance_mm[use][acc]))


LOCAL_BATCH = 2000  # points per local-model update: its kernels' working set stays small


def local_fit(points, shape, beams=None):
    """Step 6 of the module docstring: the LocalField (models.local.field) of the points
    (N, 3) mm about the global `shape` (Sphere or Ellipsoid in W), or None without a
    shape or points; `beams`: None or their beams' directions (N, 3) in W."""
    from models.local.field import LocalField
    from models.local.grid import LocalRetinaModel

    if shape is None or not len(points):
        return None
    local = LocalRetinaModel(shape.center)
    for k in range(0, len(points), LOCAL_BATCH):
        local.update(np.ascontiguousarray(points[k:k + LOCAL_BATCH]), shape,
                     beam_W=None if beams is None else np.ascontiguousarray(beams[k:k + LOCAL_BATCH]))
    if local.global_params is None:  # the shape does not hold its centre: no local frame
        return None
    local.solve_all()
    return LocalField(local.params(True), "local")
