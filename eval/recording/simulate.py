"""A simulated rig recording: what a Meca500 + iiOCT rig writes while it synchronises
its streams and scans the spiral, as a ROS 2 bag, with the run's ground truth apart.

The true motion (`scan` "surgery": the surgery scenario, planning.scenario, the spiral
through the trocar; "phantom": a printed lower half open on the bench, planning.phantom,
the spiral above the cup with the shaft through a pivot in the air): a rest at the
spiral's start posture, the synchronisation motion (planning.clock_sync: the tip in and
out along the shaft, an amplitude-modulated sinusoid), the spiral (differential
kinematics keeping the shaft on the trocar or pivot at the joint rate,
planning.scan.run_diffik), a rest. The robot publishes its
joint angles at `joint_rate_hz` stamped on its clock, with encoder noise; the OCT makes
an A-scan at `oct_rate_hz` from the TRUE sensor pose (the scenario's calibration error)
on the true eye (models.iioct synthesis), stamped on its clock: true time plus the time
offset. The bag (eval.recording.bag) never holds the truth: `truth` returns it for a
separate JSON.

Units: mm, s, rad (ms, um, urad where named).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from eval.recording import SCANS
from eval.recording.bag import BagWriter, counts_of
from models.iioct import synthesize_ascan
from planning.clock_sync import SYNC_AMPLITUDE_MM, SYNC_CARRIER_HZ, SYNC_DURATION_S, sync_joint_path

# Both clocks count from the same epoch (ROS time of 2025-06-15); a stamp is never negative
EPOCH_S = 1_750_000_000.0
NO_RETINA_MM = 1e3  # a retina this far away lies beyond the imaging depth: the scan holds none
# Meca500 repeatability 5 um at the tip ~300 mm from the shoulder: ~1.7e-5 rad per joint
ENCODER_NOISE_RAD = 2e-5


@dataclass(frozen=True)
class RecordingSpec:
    """What to record: the eye (`shape`, its `eye_params`), the scene (`scan`: "surgery",
    the eye in the head entered through the trocar, or "phantom", its printed lower half on
    the bench scanned from above; module docstring), the eye's placement (`eye_pose`:
    X_WE as a rotation vector (rad) and a position (mm), 6 numbers; None: the scene's
    default, planning.scenario.SURGERY_EYE_POSE or planning.phantom.PHANTOM_EYE_POSE), the OCT clock's offset
    (s, OCT minus robot: positive when the OCT stream lags), the seed, the encoder noise
    (rad SD per joint), the streams' rates (Hz), the spiral (pitch mm, revolutions, tip
    speed mm/s), the synchronisation motion (amplitude mm, carrier Hz, duration s) and
    the rests before and after (s)."""

    shape: str = "emmetropic"
    eye_params: dict = field(default_factory=dict)
    scan: str = "surgery"
    eye_pose: tuple | None = None
    time_offset_s: float = 0.0
    seed: int = 0
    encoder_noise_rad: float = ENCODER_NOISE_RAD
    joint_rate_hz: float = 1000.0
    oct_rate_hz: float = 2000.0
    pitch_mm: float = 1.5
    revolutions: float = 6.0
    speed_mm_s: float = 15.0
    sync_amplitude_mm: float = SYNC_AMPLITUDE_MM
    sync_carrier_hz: float = SYNC_CARRIER_HZ
    sync_s: float = SYNC_DURATION_S
    rest_s: float = 0.2


@dataclass(frozen=True)
class TrueMotion:
    """The robot's true joint angles q (K, 6) rad at true times t (K,) s (the joint
    rate), and the synchronisation motion's span [sync_start_s, sync_end_s]."""

    t: np.ndarray
    q: np.ndarray
    sync_start_s: float
    sync_end_s: float


def scenario_of(spec: RecordingSpec):
    """The scenario of `spec`'s eye and scene: planning.SurgeryScenario ("surgery") or
    planning.phantom.PhantomScenario ("phantom"); ValueError naming the scenes otherwise."""
    from planning import SurgeryScenario
    from planning.phantom import PhantomScenario

    if spec.scan not in SCANS:
        raise ValueError(f"scan must be one of {', '.join(SCANS)}, got {spec.scan!r}")
    kind = SurgeryScenario if spec.scan == "surgery" else PhantomScenario
    placed = {}
    if spec.eye_pose is not None:
        from scipy.spatial.transform import Rotation

        from models.eyes import EyePose

        v = np.asarray(spec.eye_pose, dtype=float)
        placed["eye_pose"] = EyePose(Rotation.from_rotvec(v[:3]).as_matrix(), v[3:])
    return kind(eye_name=spec.shape, eye_params=dict(spec.eye_params), **placed)


def true_motion(robot, scenario, spec: RecordingSpec) -> TrueMotion:
    """The true joint trajectory (module docstring) sampled at spec.joint_rate_hz."""
    from planning.scan import run_diffik, start_posture

    dt = 1.0 / spec.joint_rate_hz
    P = scenario.eye_pose.to_W(scenario.spiral_E(spec.pitch_mm, spec.revolutions, 0.1))
    q0 = start_posture(robot, P[0], scenario.p_WC)
    phantom = spec.scan == "phantom"
    if phantom:  # two passes with the instrument turned about its shaft between them (planning.phantom)
        from planning.phantom import return_pass, rolled

        q0 = rolled(q0)
    n_rest, n_sync = int(round(spec.rest_s / dt)), int(round(spec.sync_s / dt))
    Q_sync = sync_joint_path(robot, q0, np.arange(n_sync + 1) * dt, amplitude_mm=spec.sync_amplitude_mm,
                             carrier_hz=spec.sync_carrier_hz, duration_s=spec.sync_s)
    scan = run_diffik(robot, P, scenario.p_WC, Q_sync[-1], spec.speed_mm_s, rate_hz=spec.joint_rate_hz)
    Q_scan = scan.q[1:]
    if phantom:
        Q_scan = np.vstack([Q_scan, return_pass(robot, P, scenario.p_WC, Q_scan[-1], spec.speed_mm_s, spec.joint_rate_hz)])
    Q = np.vstack([np.repeat(q0[None], n_rest, axis=0), Q_sync, Q_scan, np.repeat(Q_scan[-1:], n_rest, axis=0)])
    return TrueMotion(np.arange(len(Q)) * dt, Q, n_rest * dt, (n_rest + n_sync) * dt)


def _at(t: np.ndarray, motion: TrueMotion) -> np.ndarray:
    """(M, 6) rad: the true joint angles at times t (M,) s (linear between samples)."""
    return np.column_stack([np.interp(t, motion.t, motion.q[:, i]) for i in range(6)])


def write_recording(path, spec: RecordingSpec, progress=None, block_s: float = 0.5) -> dict:
    """Simulate `spec` and write its bag to `path` (a folder that must not exist); returns
    the ground truth (truth.json's content). `progress(done_s, total_s)`: called per block
    of `block_s` true seconds."""
    from planning import Robot
    from planning.iioct import IioctSensor

    scenario = scenario_of(spec)
    robot = Robot(scenario)
    motion = true_motion(robot, scenario, spec)
    sensor = IioctSensor(robot, mode="ascan", seed=spec.seed)
    rng = np.random.default_rng(spec.seed)
    Q_reported = motion.q + spec.encoder_noise_rad * rng.standard_normal(motion.q.shape)
    T_oct = np.arange(0.0, motion.t[-1], 1.0 / spec.oct_rate_hz)
    engine = sensor.engine
    end = float(motion.t[-1])
    n_blocks = int(np.ceil(end / block_s))
    with BagWriter(path) as bag:
        for b in range(n_blocks):
            lo, hi = b * block_s, min((b + 1) * block_s, end + 1e-9)
            k_j = np.flatnonzero((motion.t >= lo) & (motion.t < hi) if b < n_blocks - 1 else (motion.t >= lo))
            k_o = np.flatnonzero((T_oct >= lo) & (T_oct < hi))
            d_true, incidence = sensor.true_geometry(_at(T_oct[k_o], motion)) if len(k_o) else (np.empty(0), np.empty(0))
            scans = [synthesize_ascan(d if np.isfinite(d) else NO_RETINA_MM, a if np.isfinite(a) else 0.0, rng,
                                      engine=engine) for d, a in zip(d_true.tolist(), incidence.tolist())]
            # both streams in stamp order: the robot's on its clock (true time), the OCT's offset
            events = [(EPOCH_S + float(motion.t[k]), 0, k) for k in k_j] + [
                (EPOCH_S + float(T_oct[k]) + spec.time_offset_s, 1, i) for i, k in enumerate(k_o)]
            for stamp, kind, k in sorted(events):
                if kind == 0:
                    bag.joints(stamp, Q_reported[k])
                else:
                    bag.ascan(stamp, counts_of(scans[k], engine.full_scale))
            if progress is not None:
                progress(min(hi, end), end)
    return truth_of(spec, scenario, robot, motion, len(T_oct))


def truth_of(spec: RecordingSpec, scenario, robot, motion: TrueMotion, n_ascans: int) -> dict:
    """The recording's ground truth (truth.json): the spec, the eye's placement X_WE, the
    trocar (the phantom's pivot), the true and nominal sensor poses in the flange frame, the sync span."""
    q0 = np.zeros(6)
    R_WF, p_WF = robot.pose("F", q0)
    poses = {}
    for key, frame in (("true", "S_true"), ("nominal", "S")):
        R_WS, p_WS = robot.pose(frame, q0)
        poses[key] = {"p_FS_mm": (R_WF.T @ (p_WS - p_WF)).tolist(), "u_F": (R_WF.T @ R_WS[:, 2]).tolist()}
    out = asdict(spec)
    out.update({
        "time_offset_ms": 1e3 * spec.time_offset_s,
        "R_WE": scenario.eye_pose.R_WE.tolist(), "p_WE_mm": scenario.eye_pose.p_WE.tolist(),
        "p_WC_mm": scenario.p_WC.tolist(),
        "sensor": poses,
        "calibration_error": {"sensor_offset_S_mm": scenario.sensor_offset_S_mm.tolist(),
                              "sensor_rotvec_S_rad": scenario.sensor_rotvec_S_rad.tolist()},
        "clock_epoch_s": EPOCH_S,
        "sync_true_s": [motion.sync_start_s, motion.sync_end_s],
        "duration_s": float(motion.t[-1]), "n_joint_states": len(motion.t), "n_ascans": n_ascans,
    })
    return out


def direct_model(spec: RecordingSpec, true_sensor_pose: bool = False, progress=None):
    """The reference of a recording's fit: the model the closed loop's own sensor and model
    chain builds from the same scan without the recording round trip (no bag, no clock
    offset, no synchronisation estimate, no registration). The same true motion as
    `write_recording` (the scan after the synchronisation motion), the loop's sensor
    (planning.iioct.IioctSensor, "ascan" mode, spec.seed, spec.encoder_noise_rad on the
    reported angles, the nominal sensor pose for the points: the scenario's calibration
    error reaches the points as in the fit without --calibration; `true_sensor_pose`: the
    true one, a perfect calibration) sampled at the OCT rate
    in packets of 20 (the loop's), and the loop's model (AdaptiveEyeModel, predictive
    criteria, the quadric: ClosedLoop.new_model) updated with each packet's valid points.
    The safety filter is left out: it would change the motion, and the reference is the
    same scan trajectory. Returns the AdaptiveEyeModel in W. `progress(done, total)`:
    called per packet block."""
    from models import AdaptiveEyeModel
    from models.adaptive.transition import PredictiveCriteria
    from planning import Robot
    from planning.iioct import IioctSensor

    scenario = scenario_of(spec)
    robot = Robot(scenario)
    motion = true_motion(robot, scenario, spec)
    sensor = IioctSensor(robot, mode="ascan", seed=spec.seed, encoder_noise_rad=spec.encoder_noise_rad,
                         X_S_Scal=scenario.X_S_Strue if true_sensor_pose else None)
    T = np.arange(0.0, motion.t[-1], 1.0 / spec.oct_rate_hz)
    T = T[T > motion.sync_end_s]
    Q = _at(T, motion)
    model = AdaptiveEyeModel(criteria=PredictiveCriteria())
    packet = 20
    for k in range(0, len(T), packet):
        Qk = np.ascontiguousarray(Q[k:k + packet])
        p = sensor.packet_of_arrays(np.ascontiguousarray(T[k:k + packet]), Qk, Qk.copy())
        if p.valid.any():
            model.update(np.ascontiguousarray(p.p_W[p.valid]), np.ascontiguousarray(p.beam_dir_W[p.valid]))
        if progress is not None and (k // packet) % 100 == 0:
            progress(k, len(T))
    return model
