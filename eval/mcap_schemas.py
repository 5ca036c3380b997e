"""JSON schemas of the run log's channels (MCAP, JSON message encoding).

Our channels carry mm, s, rad (W frame) and a time `t` in s; "/tf" and "/scene" use
Foxglove's well-known schemas foxglove.FrameTransforms and foxglove.SceneUpdate (named
exactly so, which is how Foxglove recognises them), in metres as Foxglove expects.
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

# --- Foxglove well-known types (field names and layout from the Foxglove schema docs) ---
TIME = obj(required=("sec", "nsec"), sec={"type": "integer", "minimum": 0},
           nsec={"type": "integer", "minimum": 0, "maximum": 999_999_999})
VEC3 = obj(required=("x", "y", "z"), x=NUM, y=NUM, z=NUM)
QUAT = obj(required=("x", "y", "z", "w"), x=NUM, y=NUM, z=NUM, w=NUM)
COLOR = obj(required=("r", "g", "b", "a"), r=NUM, g=NUM, b=NUM, a=NUM)
POSE = obj(position=VEC3, orientation=QUAT)
FRAME_TRANSFORM = obj("foxglove.FrameTransform", timestamp=TIME, parent_frame_id=STR, child_frame_id=STR,
                      translation=VEC3, rotation=QUAT)
SPHERE_PRIMITIVE = obj("foxglove.SpherePrimitive: size is the diameter along each axis", pose=POSE, size=VEC3,
                       color=COLOR)
LINE_PRIMITIVE = obj("foxglove.LinePrimitive", type={"type": "integer", "description": "0 strip, 1 loop, 2 list"},
                     pose=POSE, thickness=NUM, scale_invariant=BOOL, points=arr(VEC3), color=COLOR,
                     colors=arr(COLOR), indices=arr(INT))
SCENE_ENTITY = obj(
    "foxglove.SceneEntity", timestamp=TIME, frame_id=STR, id=STR, lifetime=TIME, frame_locked=BOOL,
    metadata=arr(obj(key=STR, value=STR)), arrows=arr(obj()), cubes=arr(obj()), spheres=arr(SPHERE_PRIMITIVE),
    cylinders=arr(obj()), lines=arr(LINE_PRIMITIVE), triangles=arr(obj()), texts=arr(obj()), models=arr(obj()))

FOXGLOVE = {
    "foxglove.FrameTransforms": obj("A list of transforms", transforms=arr(FRAME_TRANSFORM)),
    "foxglove.SceneUpdate": obj("An update to the entities displayed in a 3D scene",
                                deletions=arr(obj(timestamp=TIME, type=INT, id=STR)), entities=arr(SCENE_ENTITY)),
}

# --- our channels: topic -> (schema name, schema) ---
CHANNELS = {
    "/filter/config": ("vitreoguard.FilterConfig", obj(
        "safety.FilterConfig fields (mm, s, rad)",
        **{f.name: STR if isinstance(f.default, str) else EXACT for f in dataclasses.fields(FilterConfig)})),
    "/robot/joint_states": ("vitreoguard.JointStates", obj(
        "joint angles and rates", ("t", "names", "q", "qdot"), t=NUM, names=arr(STR), q=arr(NUM, "rad"),
        qdot=arr(NUM, "rad/s"))),
    "/oct/ascan": ("vitreoguard.AScan", obj(
        "one A-scan", ("t", "n_samples", "samples", "valid", "reason"), t=NUM, n_samples=INT,
        samples={"type": "string", "contentEncoding": "base64", "description": "float32 little-endian intensities"},
        valid=BOOL, reason=STR)),
    "/oct/distance": ("vitreoguard.Distance", obj(
        "distance extracted from an A-scan", ("t", "distance_mm", "valid", "confidence"), t=NUM,
        distance_mm=OPT_NUM, valid=BOOL, confidence=OPT_NUM)),
    "/model": ("vitreoguard.EyeModel", obj(
        "adaptive eye model state (W, mm)", ("t", "kind", "kind_index", "n_points"), t=NUM, kind=STR,
        kind_index={"type": "integer", "description": "0 prior, 1 sphere, 2 ellipsoid (for plots)"},
        n_points=INT, sphere=SHAPE, ellipsoid=SHAPE,
        criteria={"type": "object", "description": "criterion name -> {value, met}"})),
    "/filter/inputs": ("vitreoguard.FilterInputs", obj(
        "every safety.FilterInputs field of one step (W; mm, s, rad)", ("t", "step"), t=NUM, step=INT,
        t_s=EXACT, q=arr(EXACT), q_min=arr(EXACT), q_max=arr(EXACT), qdot_max=arr(EXACT), v_cmd_W=arr(EXACT),
        J_tip=MATRIX, boundary_points=POINTS, model=SHAPE, model_time_s=EXACT, sensor_time_s=EXACT,
        rcm_A={"type": ["array", "null"]}, rcm_b={"type": ["array", "null"]}, lens=SHAPE, lens_points=POINTS,
        margin_mm=EXACT, J_roll={"type": ["array", "null"]}, roll_rate_cmd=EXACT, fallback=SHAPE)),
    "/filter/outputs": ("vitreoguard.FilterOutputs", obj(
        "commanded joint rates", ("t", "step", "qdot"), t=NUM, step=INT, qdot=arr(EXACT, "rad/s"))),
    "/filter/status": ("vitreoguard.FilterStatus", obj(
        "filter activity", ("t", "step", "ok", "reason"), t=NUM, step=INT, ok=BOOL, reason=STR, active=arr(STR),
        n_active=INT, min_clearance_mm=OPT_NUM, cutter_allowed=BOOL, intervened=BOOL, solve_us=NUM)),
    "/clearance": ("vitreoguard.Clearance", obj(
        "model clearance of the tip and cutter port (mm; > 0 inside); *_true_mm against the true retina",
        ("t",), t=NUM, tip_mm=OPT_NUM, port_mm=OPT_NUM, tip_true_mm=OPT_NUM, port_true_mm=OPT_NUM)),
    "/tf": ("foxglove.FrameTransforms", FOXGLOVE["foxglove.FrameTransforms"]),
    "/scene": ("foxglove.SceneUpdate", FOXGLOVE["foxglove.SceneUpdate"]),
}
