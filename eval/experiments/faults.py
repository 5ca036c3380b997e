"""The boundary under real-robot faults: one adversarial campaign per fault class.

Each class changes the closed loop's configuration (eval.loop_config.LoopConfig: the
actuator the filter is told, the sensor's time offset and encoder noise, a degenerate
stream) or the scenario (the true sensor pose off by the declared calibration bound), or
adds vitreous floaters; the model is built by the spiral through that loop (a
calibration, offset or noise error reaches the model as it would on the robot), then
the boundary's own campaign (eval.experiments.boundary.run_campaign) attacks it. A
stream fault starts STREAM_ONSET_S into each adversarial scenario (the spiral runs on a
healthy stream).

Parameters and their sources (assumptions where the Meca500's documentation is silent):
- ideal: no fault and no calibration bound in the margin (d_safe and the model's own
  uncertainty alone): the reference every class's margin cost is measured against
  (`margin_costs`); none: no fault, the declared calibration bound in the margin.
- delay 5 ms, lag 20 ms: the largest the boundary must hold for (a velocity-mode controller's cycle and
  servo lag); the Meca500 manual states neither.
- acceleration limit 1000 deg/s^2 on every joint: assumed (the manual sets accelerations
  as a percentage, SetJointAcc, of a maximum it does not state; at 1000 deg/s^2 J1 reaches
  its top speed of 150 deg/s in 0.15 s). The filter's braking margin grows as v^2 / (2 a):
  at 300 deg/s^2 the model the spiral built on the emmetropic eye (seed 4242) left only 60
  of 100 adversarial starts reachable.
- calibration: the true sensor 1 x the declared bound behind its calibrated origin along
  the beam (every point measured that much too deep: the model outside the retina, the
  dangerous sign) and its beam turned by the declared angle about S's x axis.
- OCT time offset 2.6 ms: the paper's largest measured.
- encoder noise 0.001 deg SD: assumed from the Meca500's 5 um position repeatability
  (Mecademic) over its ~0.3 m reach.
- dropout, frozen, invalid, stuck_clock: planning.iioct.stream.StreamFault from
  STREAM_ONSET_S on.
- floaters: 2 % of the samples (planning.iioct.IioctSensor's worst case in "distance"
  mode: a confident wrong distance).
- combined: every class of ROBOT_CLASSES at once, as above (the delay, the lag and the
  acceleration limit in one actuator): the errors a real robot and sensor bring together.
  The stream classes stay apart: each stops the robot within the sensor age limit, which
  would end every scenario before the others could act.
Units: mm, s, deg where named.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from eval.experiments.boundary import CAMPAIGN_KEYS, build_model_by_spiral, reason_class, run_campaign
from eval.experiments.model_report import model_summary
from planning import SurgeryScenario
from planning.iioct.stream import StreamFault
from safety.actuator import ActuatorModel

STREAM_ONSET_S = 0.1
ACCEL_LIMIT_DEG_S2 = 1000.0
ENCODER_NOISE_DEG = 0.001
FLOATER_RATE = 0.02
ROBOT_CLASSES = ("delay", "lag", "accel_limit", "calibration", "time_offset", "encoder_noise", "floaters")
STREAM_CLASSES = ("dropout", "frozen", "invalid", "stuck_clock")
FAULT_CLASSES = ("ideal", "none", "delay", "lag", "accel_limit", "calibration", "time_offset", "encoder_noise", "dropout",
                 "frozen", "invalid", "stuck_clock", "floaters", "combined")


@dataclasses.dataclass(frozen=True)
class FaultClass:
    """One class: its `parameters` (for faults.json), the loop configurations of the model's
    spiral (`build`) and of the adversarial campaign (`campaign`), the scenario's keyword
    arguments (SurgeryScenario) and the floater rate."""

    name: str
    parameters: dict
    build: object
    campaign: object
    scenario_kwargs: dict
    floater_rate: float = 0.0


_ACTUATOR = {"delay": {"delay_s": 0.005}, "lag": {"lag_s": 0.020},
             "accel_limit": {"accel_limit_rad_s2": float(np.radians(ACCEL_LIMIT_DEG_S2))}}


def _errors(name: str, base) -> tuple[dict, dict, dict, dict, float]:
    """One error class of ROBOT_CLASSES as (parameters, LoopConfig changes, ActuatorModel
    keyword arguments, scenario keyword arguments, floater rate)."""
    if name in _ACTUATOR:
        return {}, {}, _ACTUATOR[name], {}, 0.0
    if name == "calibration":
        mm, deg = base.filter.calibration_bound_mm, base.filter.calibration_bound_deg
        error = [0.0, 0.0, -mm, deg, 0.0, 0.0]
        return ({"sensor_pose_error": error, "calibration_bound": [mm, deg]}, {}, {},
                {"sensor_offset_S_mm": np.array(error[:3]), "sensor_rotvec_S_rad": np.radians(error[3:])}, 0.0)
    if name == "time_offset":
        return {"oct_time_offset_ms": 2.6}, {"oct_time_offset_s": 0.0026}, {}, {}, 0.0
    if name == "encoder_noise":
        noise_rad = float(np.radians(ENCODER_NOISE_DEG))
        return {"encoder_noise_deg": ENCODER_NOISE_DEG}, {"encoder_noise_rad": noise_rad}, {}, {}, 0.0
    if name == "floaters":
        return {"floater_rate": FLOATER_RATE}, {}, {}, {}, FLOATER_RATE
    raise ValueError(f"{name!r} is not one of ROBOT_CLASSES: {', '.join(ROBOT_CLASSES)}")


def fault_class(name: str, base) -> FaultClass:
    """The class `name` (FAULT_CLASSES) on the base LoopConfig (module docstring)."""
    if name == "ideal":
        cfg = dataclasses.replace(base, filter=dataclasses.replace(base.filter, calibration_bound_mm=0.0,
                                                                  calibration_bound_deg=0.0))
        return FaultClass(name, {"calibration_bound": [0.0, 0.0]}, cfg, cfg, {})
    if name == "none":
        return FaultClass(name, {}, base, base, {})
    if name in STREAM_CLASSES:
        cfg = dataclasses.replace(base, stream_fault=StreamFault(name, STREAM_ONSET_S))
        return FaultClass(name, {"stream_fault": name, "onset_s": STREAM_ONSET_S}, base, cfg, {})
    if name not in ROBOT_CLASSES and name != "combined":
        raise ValueError(f"unknown fault class {name!r}; choose from {', '.join(FAULT_CLASSES)}")
    parameters, changes, actuator, scenario_kwargs, floater_rate = {}, {}, {}, {}, 0.0
    for part in ROBOT_CLASSES if name == "combined" else (name,):
        p, c, a, k, r = _errors(part, base)
        parameters.update(p)
        changes.update(c)
        actuator.update(a)
        scenario_kwargs.update(k)
        floater_rate = max(floater_rate, r)
    if actuator:
        model = changes["actuator"] = ActuatorModel(**actuator)
        parameters = {"actuator_delay_ms": 1e3 * model.delay_s, "actuator_lag_ms": 1e3 * model.lag_s,
                      "actuator_accel_limit_deg_s2": ACCEL_LIMIT_DEG_S2 if "accel_limit_rad_s2" in actuator else None,
                      **parameters}
    cfg = dataclasses.replace(base, **changes) if changes else base
    return FaultClass(name, parameters, cfg, cfg, scenario_kwargs, floater_rate)


def detection_ms(runs, onset_s: float) -> dict:
    """How long after `onset_s` each run's filter first stopped for the stream ("stale
    sensor ..."): {"max", "median", "undetected" (runs that never stopped for it)}."""
    lat, missed = [], 0
    for r in runs:
        k = next((i for i in range(len(r.t)) if r.t[i] >= onset_s and not r.ok[i]
                  and reason_class(r.reasons[i]).startswith("stale sensor")), None)
        if k is None:
            missed += 1
        else:
            lat.append(1e3 * (r.t[k] - onset_s))
    return {"max": float(max(lat)) if lat else None, "median": float(np.median(lat)) if lat else None,
            "undetected": missed}


def margin_costs(classes: dict) -> dict:
    """{class: its min_true_clearance_mm - the ideal class's} (mm) over faults.json's
    classes that ran, when "ideal" ran: what the class's margin (or fault) costs in the
    closest approach to the true retina; {} without the ideal class."""
    ideal = classes.get("ideal", {}).get("min_true_clearance_mm")
    if ideal is None:
        return {}
    return {name: c["min_true_clearance_mm"] - ideal for name, c in classes.items()
            if c.get("min_true_clearance_mm") is not None}


def run_fault_class(fc: FaultClass, shape: str, n: int, seed: int, duration_s: float, make_loop, progress=None,
                    eye_params: dict | None = None, **campaign_kwargs) -> dict:
    """The class's campaign on the `shape` eye (make_eye's shape parameters `eye_params`):
    its faults.json entry, whose "model" holds the figures of the model the filter used
    (eval.experiments.model_report.model_summary: kind, mae_um, scanned_p95_um, ...) and the
    spiral's least-squares ellipsoid's MAE. `make_loop(scenario, config, **kw)` builds a
    ClosedLoop (eval.cli.boundary.make_loop: with a progress phase); `campaign_kwargs` go to
    run_campaign (e.g. its `workers`)."""
    scenario = SurgeryScenario(eye_name=shape, eye_params=dict(eye_params or {}), **fc.scenario_kwargs)
    loop = make_loop(scenario, fc.build, sensor_seed=seed, floater_rate=fc.floater_rate)
    build = build_model_by_spiral(loop, sensor_seed=seed)
    model = {**model_summary(loop, build), "ef_mae_um": build.ef_mae_um}
    if fc.campaign is not fc.build:
        loop = make_loop(scenario, fc.campaign, sensor_seed=seed, floater_rate=fc.floater_rate)
    campaign = run_campaign(loop, build.model, build.coverage, n, seed, duration_s, progress=progress, **campaign_kwargs)
    s = campaign.summary()
    out = {"parameters": fc.parameters,
           **{k: s[k] for k in CAMPAIGN_KEYS},
           "model": model,
           "calibration_margin_mm": fc.campaign.filter.calibration_margin_mm,
           "spiral_min_true_clearance_mm": float(build.run.true_clearance_mm.min())}
    if fc.campaign.stream_fault.kind != "none":
        out["detection_ms"] = detection_ms(campaign.runs, fc.campaign.stream_fault.onset_s)
    out["min_clearance_per_run"] = [float(x) for x in campaign.min_clearance_per_run]
    return out


__all__ = ["FAULT_CLASSES", "ROBOT_CLASSES", "STREAM_CLASSES", "FaultClass",
           "detection_ms", "fault_class", "margin_costs", "run_fault_class"]
