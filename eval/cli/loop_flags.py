"""The closed loop's real-robot error flags, shared by the closed-loop commands.

`add_loop_flags(parser)` adds them; `loop_config(args, **kw)` and `scenario(args)` turn
them into an eval.loop_config.LoopConfig and a planning.SurgeryScenario:

- the actuator between the filter and the joints (safety.actuator.ActuatorModel, which
  the filter is told): --actuator-delay-ms, --actuator-lag-ms, --actuator-accel-limit
  (deg/s^2 on every joint; default none);
- the sensor: --oct-time-offset-ms (the OCT stream's lag behind the joint angles; the
  paper measured up to 2.6 ms), --encoder-noise (SD of the reported joint angles, deg);
- the model that bounds the motion: --model (local: the local-global model, d_safe + k
  sigma; quadric: the sphere, then the ellipsoid, with their phase margins);
- the calibration: --calibration-bound MM,DEG (the declared bound the filter keeps in
  its margin; default safety.FilterConfig's, 3 standard errors of the plate calibration)
  and --sensor-pose-error DX,DY,DZ,RX,RY,RZ (the true sensor pose's error in the sensor
  frame S, z along the beam: offset mm, rotation vector deg; default the scenario's
  0.02 mm, 0.1 deg).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from eval.cli.args import choice, number, numbers

# the actuator applies its delay in whole control periods (safety.actuator.ActuatorModel; the loop's: 1 kHz)
DELAY_MS = number(0.0, 50.0, "ms", step=1.0)
LAG_MS = number(0.0, 200.0, "ms")
# The fault classes run 1,000 deg/s^2. Below 100 a joint at the spiral's 1.5 rad/s (its wrist)
# needs 0.9 s to stop; above 1e5 (1,745 rad/s^2) it stops from there within one 1 ms step, so
# the limit no longer acts.
ACCEL = number(100.0, 1e5, "deg/s^2")
OFFSET_MS = number(0.0, 100.0, "ms")

ENCODER_NOISE = number(0.0, 1.0, "deg")
CALIBRATION_BOUND = numbers(("MM", "DEG"), 0.0, 10.0, "(mm, deg)")
POSE_ERROR = numbers(("DX", "DY", "DZ", "RX", "RY", "RZ"), -10.0, 10.0, "(mm, deg)")
# the flags' defaults: the ideal loop (a Namespace without the flags gets these)
DEFAULTS = {"actuator_delay_ms": 0.0, "actuator_lag_ms": 0.0, "actuator_accel_limit": None, "oct_time_offset_ms": 0.0,
            "encoder_noise": 0.0, "calibration_bound": None, "sensor_pose_error": None, "model": "local"}
# what --model names: the local-global model (models.local; the filter keeps d_safe + k sigma from it) or the
# quadric (the sphere, then the ellipsoid; the filter keeps the phase margins, the trust angle and the misfit rule)
MODELS = ("local", "quadric")


def flags(args) -> dict:
    """The flags' values of `args` (DEFAULTS for those it lacks)."""
    return {k: getattr(args, k, v) for k, v in DEFAULTS.items()}


def local_model(args) -> bool:
    """Whether `args` bound the motion by the local-global model (--model local, the default)."""
    return flags(args)["model"] == "local"


def add_model_flag(p, default: str = "local") -> None:
    """--model on parser `p` (MODELS; `default`)."""
    p.add_argument("--model", type=choice("model", MODELS), default=default,
                   help="what bounds the motion: local (the local-global model, the filter keeping d_safe + 3 sigma "
                        "from it) or quadric (the sphere, then the ellipsoid, with their phase margins, trust angle and "
                        "misfit margin); README: the measured safety of both")


def add_loop_flags(p) -> None:
    """The real-robot error flags (module docstring) on parser `p`."""
    p.add_argument("--actuator-delay-ms", type=DELAY_MS, default=0.0,
                   help=f"pure delay of the robot's velocity controller, {DELAY_MS.range}")
    p.add_argument("--actuator-lag-ms", type=LAG_MS, default=0.0,
                   help=f"first-order lag (time constant) of the applied joint velocity, {LAG_MS.range}")
    p.add_argument("--actuator-accel-limit", type=ACCEL, default=None,
                   help=f"joint acceleration limit, every joint, {ACCEL.range}; default none")
    p.add_argument("--oct-time-offset-ms", type=OFFSET_MS, default=0.0,
                   help=f"OCT stream's time offset behind the joint angles, {OFFSET_MS.range} (paper: up to 2.6 ms)")
    p.add_argument("--encoder-noise", type=ENCODER_NOISE, default=0.0,
                   help=f"SD of the noise on the reported joint angles, {ENCODER_NOISE.range}")
    p.add_argument("--calibration-bound", type=CALIBRATION_BOUND, default=None, metavar="MM,DEG",
                   help=f"declared bound of the sensor calibration error the filter keeps in its margin, "
                        f"{CALIBRATION_BOUND.range}; default 0.03,0.13 (3 standard errors of the plate calibration)")
    add_model_flag(p)
    p.add_argument("--sensor-pose-error", type=POSE_ERROR, default=None, metavar="DX,DY,DZ,RX,RY,RZ",
                   help=f"true sensor pose error in S (z along the beam), {POSE_ERROR.range}; "
                        "default 0.02,0,0,0,0.1,0 (the plate calibration's accuracy)")


def actuator(args):
    """The safety.actuator.ActuatorModel of the flags."""
    from safety.actuator import ActuatorModel

    f = flags(args)
    accel = np.inf if f["actuator_accel_limit"] is None else float(np.radians(f["actuator_accel_limit"]))
    return ActuatorModel(f["actuator_delay_ms"] * 1e-3, f["actuator_lag_ms"] * 1e-3, accel)


def loop_config(args, **kwargs):
    """The LoopConfig of the flags (and `kwargs`, LoopConfig's other fields)."""
    from eval.loop_config import LoopConfig

    from eval.loop_config import default_filter

    f = flags(args)
    kwargs.setdefault("local_model", local_model(args))
    filt = kwargs.pop("filter", None) or default_filter(kwargs["local_model"])  # the loop's own defaults
    if f["calibration_bound"] is not None:
        filt = dataclasses.replace(filt, calibration_bound_mm=f["calibration_bound"][0],
                                   calibration_bound_deg=f["calibration_bound"][1])
    return LoopConfig(filter=filt, actuator=actuator(args), oct_time_offset_s=f["oct_time_offset_ms"] * 1e-3,
                      encoder_noise_rad=float(np.radians(f["encoder_noise"])), **kwargs)


def scenario(args, **kwargs):
    """The SurgeryScenario of --shape and --sensor-pose-error (and `kwargs`)."""
    from planning import SurgeryScenario

    error = flags(args)["sensor_pose_error"]
    if error is not None:
        e = np.asarray(error, dtype=float)
        kwargs.update(sensor_offset_S_mm=e[:3], sensor_rotvec_S_rad=np.radians(e[3:]))
    return SurgeryScenario(eye_name=args.shape, **kwargs)


def loop_record(args, config) -> dict:
    """The loop's real-robot errors for a results file: the flags (the true sensor pose's
    error the scenario's default when --sensor-pose-error is not given: offset mm, rotation
    vector deg) and the margin the filter keeps for the calibration bound (mm)."""
    from planning.scenario import SENSOR_OFFSET_S_MM, SENSOR_ROTVEC_S_RAD

    f = flags(args)
    if f["sensor_pose_error"] is None:  # the scenario's default true error, in the flag's units (mm, deg)
        f = {**f, "sensor_pose_error": [*map(float, SENSOR_OFFSET_S_MM), *map(float, np.degrees(SENSOR_ROTVEC_S_RAD))]}
    return {**f, "calibration_bound": [config.filter.calibration_bound_mm, config.filter.calibration_bound_deg],
            "calibration_margin_mm": config.filter.calibration_margin_mm}
