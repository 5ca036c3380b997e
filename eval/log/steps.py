"""Compact filter-step records of the closed loop's log, and what rebuilds the filter's
inputs from them.

A closed-loop step is logged as what the filter cannot recompute: the time, the joint
angles, the command, the model's and sensor's times, the margin, the trusted flag and
measured misfit of each boundary point, the actuator's pending displacements (none for an
ideal actuator), the output (joint rates, ok, reason, active constraints, cutter
interlock) and, on the local boundary, its field's distances and gradients at the boundary
points (what the filter read of a field whose nodes are ~1 MB); one "/filter/step" message
(protobuf, schema FILTER_STEP_SCHEMA, ~250 bytes, ~650 with the field's values) per step.
The model the filter used goes to "/filter/models" (JSON) once per change, numbered (the
local boundary's as STEP_VALUES, once per kind); the scenario and monitored points go
to "/filter/setup" (JSON) once. Replay rebuilds the kinematics (monitored points, their
Jacobians, the RCM rows) from the joint angles on the logged scenario's robot with the
loop's own code (eval.systems.filter.FilterSystem.inputs_from), then the FilterInputs.

Units: mm, s, rad; frame W.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from eval.log import codec
from models.local.field import FieldValues

STEP_TOPIC, MODELS_TOPIC, SETUP_TOPIC = "/filter/step", "/filter/models", "/filter/setup"
STEP_TYPE = "vitreoguard.FilterStep"

# (name, protobuf type, repeated, description): the step message's fields, numbered in order
_D, _B, _S, _U = (descriptor_pb2.FieldDescriptorProto.TYPE_DOUBLE, descriptor_pb2.FieldDescriptorProto.TYPE_BOOL,
                  descriptor_pb2.FieldDescriptorProto.TYPE_STRING, descriptor_pb2.FieldDescriptorProto.TYPE_UINT32)
STEP_FIELDS = (
    ("t", _D, False), ("step", _U, False), ("q", _D, True), ("v_cmd_W", _D, True), ("roll_rate_cmd", _D, False),
    ("model_index", _U, False), ("model_time_s", _D, False), ("sensor_time_s", _D, False), ("margin_mm", _D, False),
    ("trusted", _B, True), ("misfit_mm", _D, True), ("qdot", _D, True), ("ok", _B, False), ("reason", _S, False),
    ("active", _S, True), ("min_clearance_mm", _D, False), ("cutter_allowed", _B, False),
    ("intervened", _B, False), ("solve_us", _D, False), ("pending_rad", _D, True), ("field_h", _D, True),
    ("field_g", _D, True),
)
# The /filter/models shape of a local boundary's steps: the field's answers at the step's
# boundary points are in each step record (field_h mm, field_g row-major; values_of).
STEP_VALUES = {"kind": "step_values"}


def _file_descriptor() -> descriptor_pb2.FileDescriptorProto:
    f = descriptor_pb2.FileDescriptorProto(name="vitreoguard/filter_step.proto", package="vitreoguard", syntax="proto3")
    msg = f.message_type.add(name="FilterStep")
    for number, (name, kind, repeated) in enumerate(STEP_FIELDS, start=1):
        label = descriptor_pb2.FieldDescriptorProto.LABEL_REPEATED if repeated else descriptor_pb2.FieldDescriptorProto.LABEL_OPTIONAL
        msg.field.add(name=name, number=number, type=kind, label=label, json_name=name)
    return f


_FILE = _file_descriptor()
FILTER_STEP_SCHEMA = descriptor_pb2.FileDescriptorSet(file=[_FILE]).SerializeToString()  # MCAP schema data
_POOL = descriptor_pool.DescriptorPool()
_POOL.Add(_FILE)
FilterStep = message_factory.GetMessageClass(_POOL.FindMessageTypeByName(STEP_TYPE))


def encode_step(step: int, t_s: float, q, command, model_index: int, model_time_s: float, sensor_time_s: float,
                margin_mm: float, trusted, misfit_mm, output, pending=None, values=None) -> bytes:
    """One step's record: `command` (4,) [v_W mm/s, roll rad/s], the boundary points'
    `trusted` flags and `misfit_mm`, the filter's `output` (safety.FilterOutput), the
    actuator's `pending` displacements (r, 6) rad, row-major (None or no rows: an ideal
    actuator; decode with pending_of), the local field's `values` at the boundary points
    (models.local.field.FieldValues; None for a shape logged on /filter/models; decode
    with values_of)."""
    floats = lambda a: a.tolist() if type(a) is np.ndarray and a.dtype == np.float64 else [float(x) for x in a]  # noqa: E731
    return FilterStep(  # protobuf takes Python scalars: ndarray.tolist() is the cheapest way there
        t=float(t_s), step=int(step), q=floats(q), v_cmd_W=floats(command[:3]), roll_rate_cmd=float(command[3]),
        model_index=int(model_index), model_time_s=float(model_time_s), sensor_time_s=float(sensor_time_s),
        margin_mm=float(margin_mm), trusted=[bool(x) for x in trusted], misfit_mm=floats(misfit_mm),
        qdot=floats(output.qdot), ok=bool(output.ok), reason=str(output.reason), active=[str(a) for a in output.active],
        min_clearance_mm=float(output.min_clearance_mm), cutter_allowed=bool(output.cutter_allowed),
        intervened=bool(output.intervened), solve_us=float(output.solve_us),
        pending_rad=() if pending is None else floats(np.ravel(pending)),
        field_h=() if values is None else floats(values.h), field_g=() if values is None else floats(values.g.ravel()),
    ).SerializeToString()


def pending_of(m) -> np.ndarray | None:
    """The actuator's pending displacements (r, 6) rad of a decoded step, None for an ideal
    actuator; ValueError when the record's count is not whole rows."""
    if not len(m.pending_rad):
        return None
    if len(m.pending_rad) % 6:
        raise ValueError(f"pending_rad holds {len(m.pending_rad)} numbers, not rows of 6 joints")
    return np.array(m.pending_rad).reshape(-1, 6)


def values_of(m, P_W):
    """The FieldValues of a decoded step's field_h, field_g at its boundary points P_W
    (K, 3) mm (replay's kinematics at the step's joint angles); ValueError when the record
    does not hold K distances and K gradients."""
    if len(m.field_h) != len(P_W) or len(m.field_g) != 3 * len(P_W):
        raise ValueError(f"{len(P_W)} boundary points, but field_h holds {len(m.field_h)} distances and field_g "
                         f"{len(m.field_g)} numbers")
    return FieldValues(P_W, np.array(m.field_h), np.array(m.field_g).reshape(-1, 3))


def model_from_json(d):
    """A /filter/models record's shape: STEP_VALUES (the values are in each step record)
    or codec.shape_from_json's Sphere, Ellipsoid, FieldValues or None; ValueError."""
    return STEP_VALUES if d == STEP_VALUES else codec.shape_from_json(d, "/filter/models shape")


def decode_step(data: bytes):
    """The FilterStep message of encode_step's bytes; ValueError when they are not one."""
    try:
        return FilterStep.FromString(data)
    except Exception as exc:  # protobuf's DecodeError
        raise ValueError(f"not a {STEP_TYPE} record: {exc}") from None


def setup_to_json(scenario, points, trust_angle_deg: float, misfit_angle_deg: float) -> dict:
    """What rebuilds the loop's robot and monitored points: the planning.SurgeryScenario's
    fields and the planning.instrument_points.MonitoredPointsConfig."""
    pose = scenario.eye_pose
    return {"scenario": {"eye_name": scenario.eye_name, "eye_params": {str(k): float(v) for k, v in scenario.eye_params.items()},
                         "R_WE": codec.json_array(pose.R_WE),
                         "p_WE": codec.json_array(pose.p_WE), "p_EC": codec.json_array(scenario.p_EC),
                         "sensor_offset_S_mm": codec.json_array(scenario.sensor_offset_S_mm),
                         "sensor_rotvec_S_rad": codec.json_array(scenario.sensor_rotvec_S_rad)},
            "points": {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(points).items()},
            "trust_angle_deg": float(trust_angle_deg), "misfit_angle_deg": float(misfit_angle_deg)}


def setup_from_json(d) -> tuple:
    """(SurgeryScenario, MonitoredPointsConfig) of a setup_to_json dict; ValueError naming the bad field."""
    from models.eyes import EyePose
    from planning import SurgeryScenario
    from planning.instrument_points import MonitoredPointsConfig

    try:
        s = d["scenario"]
        pose = EyePose(codec.array_from_json(s["R_WE"], "R_WE"), codec.array_from_json(s["p_WE"], "p_WE"))
        scenario = SurgeryScenario(
            eye_pose=pose, p_EC=codec.array_from_json(s["p_EC"], "p_EC"), eye_name=str(s["eye_name"]),
            eye_params={str(k): float(v) for k, v in s.get("eye_params", {}).items()},
            sensor_offset_S_mm=codec.array_from_json(s["sensor_offset_S_mm"], "sensor_offset_S_mm"),
            sensor_rotvec_S_rad=codec.array_from_json(s["sensor_rotvec_S_rad"], "sensor_rotvec_S_rad"))
        points = MonitoredPointsConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in d["points"].items()})
    except (KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"/filter/setup lacks or mistypes {exc}") from None
    return scenario, points
