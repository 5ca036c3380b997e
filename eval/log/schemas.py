"""JSON schemas of the run log's own channels (MCAP, JSON message encoding).

They carry mm, s, rad (W frame) and the simulation time `t` in s. Foxglove's
well-known types ("/tf", "/scene", "/log") are not here: eval.log.scene builds them
with foxglove-sdk's message classes, whose schemas are Foxglove's published ones.
"""
from __future__ import annotations

import dataclasses

from safety import FilterConfig

NUM = {"type": "number"}
INT = {"type": "integer"}
BOOL = {"type": "boolean"}
STR = {"type": "string"}
EXACT = {"type": ["number", "string"], "description": "a float; 'nan', 'inf', '-inf' for non-finite values"}
OPT_NUM = {"type": ["number", "null"]}
SIM_TIME = {"type": "number", "description": "simulation time, s (the log time is the run's wall-clock start + it)"}


def obj(description: str = "", required: tuple = (), **properties) -> dict:
    """A JSON-schema object with these properties."""
    d = {"type": "object", "properties": properties}
    if description:
        d["description"] = description
    if required:
        d["required"] = list(required)
    return d


def arr(items=NUM, description: str = "") -> dict:
    d = {"type": "array", "items": items}
    if description:
        d["description"] = description
    return d


MATRIX = arr(arr(EXACT), "rows of floats")
SHAPE = {"type": ["object", "null"], "description": "{kind: sphere, center, radius} or "
         "{kind: ellipsoid, center, radii, rotation (columns = semi-axis directions)}, mm"}
POINTS = arr(obj(name=STR, p_W=arr(EXACT), J_W=MATRIX, trusted=BOOL, margin_mm=EXACT),
             "monitored points: position mm, Jacobian mm/rad (W); trusted: the model has data near it; "
             "margin_mm: the point's extra clearance (measured local misfit)")

# topic -> (schema name, schema)
CHANNELS = {
    "/filter/config": ("vitreoguard.FilterConfig", obj(
        "safety.FilterConfig fields (mm, s, rad)",
        **{f.name: STR if isinstance(f.default, str) else EXACT for f in dataclasses.fields(FilterConfig)})),
    "/robot/joint_states": ("vitreoguard.JointStates", obj(
        "joint angles and rates", ("t", "names", "q", "qdot"), t=SIM_TIME, names=arr(STR), q=arr(NUM, "rad"),
        qdot=arr(NUM, "rad/s"))),
    "/oct/ascan": ("vitreoguard.AScan", obj(
        "one A-scan", ("t", "n_samples", "samples", "valid", "reason"), t=SIM_TIME, n_samples=INT,
        samples={"type": "string", "contentEncoding": "base64", "description": "float32 little-endian intensities"},
        valid=BOOL, reason=STR)),
    "/oct/distance": ("vitreoguard.Distance", obj(
        "distance extracted from an A-scan", ("t", "distance_mm", "valid", "confidence"), t=SIM_TIME,
        distance_mm=OPT_NUM, valid=BOOL, confidence=OPT_NUM)),
    "/model": ("vitreoguard.EyeModel", obj(
        "adaptive eye model state (W, mm)", ("t", "kind", "kind_index", "n_points"), t=SIM_TIME, kind=STR,
        kind_index={"type": "integer", "description": "0 prior, 1 sphere, 2 ellipsoid (for plots)"},
        n_points=INT, sphere=SHAPE, ellipsoid=SHAPE,
        criteria={"type": "object", "description": "criterion name -> {value, met}"})),
    "/filter/inputs": ("vitreoguard.FilterInputs", obj(
        "every safety.FilterInputs field of one step (W; mm, s, rad)", ("t", "step"), t=SIM_TIME, step=INT,
        t_s=EXACT, q=arr(EXACT), q_min=arr(EXACT), q_max=arr(EXACT), qdot_max=arr(EXACT), v_cmd_W=arr(EXACT),
        J_tip=MATRIX, boundary_points=POINTS, model=SHAPE, model_time_s=EXACT, sensor_time_s=EXACT,
        rcm_A={"type": ["array", "null"]}, rcm_b={"type": ["array", "null"]}, lens=SHAPE, lens_points=POINTS,
        margin_mm=EXACT, J_roll={"type": ["array", "null"]}, roll_rate_cmd=EXACT, fallback=SHAPE,
        pending={"type": ["array", "null"],
                 "description": "the actuator's pending joint displacements (r, n) rad; null: an ideal actuator"},
        rcm_refusal={"type": "string", "description": "the RCM rows' planned stop, empty for none"})),
    "/filter/outputs": ("vitreoguard.FilterOutputs", obj(
        "commanded joint rates", ("t", "step", "qdot"), t=SIM_TIME, step=INT, qdot=arr(EXACT, "rad/s"))),
    "/filter/status": ("vitreoguard.FilterStatus", obj(
        "filter activity", ("t", "step", "ok", "reason"), t=SIM_TIME, step=INT, ok=BOOL, reason=STR, active=arr(STR),
        n_active=INT, min_clearance_mm=OPT_NUM, cutter_allowed=BOOL, intervened=BOOL, solve_us=NUM)),
    "/filter/setup": ("vitreoguard.FilterSetup", obj(
        "the closed loop's scenario (planning.SurgeryScenario fields) and monitored points: replay rebuilds the "
        "kinematics of /filter/step records from them", ("scenario", "points"), scenario={"type": "object"},
        points={"type": "object"}, trust_angle_deg=NUM, misfit_angle_deg=NUM)),
    "/filter/models": ("vitreoguard.FilterModel", obj(
        "the model the filter used from time t on (W, mm); /filter/step's model_index names it",
        ("t", "index", "kind"), t=SIM_TIME, index=INT, kind={"type": ["string", "null"]},
        shape={"type": ["object", "null"], "description": SHAPE["description"] + "; {kind: step_values}: the local "
               "field's distances and gradients at the step's boundary points, in each /filter/step record "
               "(field_h mm, field_g row-major)"})),
    "/clearance": ("vitreoguard.Clearance", obj(
        "model clearance of the tip and cutter port (mm; > 0 inside); *_true_mm against the true retina",
        ("t",), t=SIM_TIME, tip_mm=OPT_NUM, port_mm=OPT_NUM, tip_true_mm=OPT_NUM, port_true_mm=OPT_NUM)),
}
