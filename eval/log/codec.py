"""Exact JSON forms of the safety filter's inputs, configuration and eye shapes, for the
run log and its replay.

Floats are written with Python's shortest round-trip repr, so decoding gives back the
same bits; NaN and +-inf (which JSON lacks) are written as the strings "nan", "inf",
"-inf". Units and frames are those of the objects encoded (mm, s, rad; W frame).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from models import Ellipsoid, Sphere
from models.local.field import FieldValues
from safety import FilterConfig, FilterInputs, PointKinematics

_SCALARS = ("t_s", "model_time_s", "sensor_time_s", "margin_mm", "roll_rate_cmd")
_ARRAYS = ("q", "q_min", "q_max", "qdot_max", "v_cmd_W", "J_tip")
_OPTIONAL_ARRAYS = ("rcm_A", "rcm_b", "J_roll", "pending")
_STRINGS = ("rcm_refusal",)
_POINT_LISTS = ("boundary_points", "lens_points")
_SHAPES = ("model", "lens", "fallback")
_OPTIONAL_ON_READ = ("fallback", "pending", "rcm_refusal")  # a log may lack them: read as None ("" for a string)
_NONFINITE = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}


# FilterInputs fields this format does not know (a newer safety package): logging refuses
# them rather than write logs that cannot be replayed.
_UNKNOWN_INPUT_FIELDS = sorted({f.name for f in dataclasses.fields(FilterInputs)}
                               - set(_SCALARS + _ARRAYS + _OPTIONAL_ARRAYS + _STRINGS + _POINT_LISTS + _SHAPES))


def json_number(x) -> float | str:
    """A float, or "nan"/"inf"/"-inf" for the values JSON cannot hold."""
    v = float(x)
    return v if math.isfinite(v) else ("nan" if v != v else ("inf" if v > 0 else "-inf"))


def json_array(a) -> list:
    """Nested lists of floats (non-finite values as strings) of the float array `a`."""
    A = np.asarray(a, dtype=float)
    if np.isfinite(A).all():
        return A.tolist()
    return np.array([json_number(v) for v in A.ravel()], dtype=object).reshape(A.shape).tolist()


def number_from_json(x, name: str) -> float:
    """The float of a json_number, or ValueError naming `name`."""
    if isinstance(x, str) and x in _NONFINITE:
        return _NONFINITE[x]
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        raise ValueError(f"{name} must be a number, got {x!r}")
    return float(x)


def array_from_json(x, name: str) -> np.ndarray:
    """The float array (ndim >= 1) of a json_array, or ValueError naming `name`."""
    try:
        A = np.array(x, dtype=float)  # also parses the strings "nan", "inf", "-inf"
    except (ValueError, TypeError):
        A = None
    if A is None or A.ndim == 0:
        raise ValueError(f"{name} must be a (nested) list of numbers, got {str(x)[:60]}")
    return A


def shape_to_json(shape) -> dict | None:
    """{"kind": "sphere", center, radius}, {"kind": "ellipsoid", center, radii, rotation}
    (mm; rotation columns are the semi-axis directions) or {"kind": "values", points, h, g}
    (models.local.field.FieldValues); None for None."""
    if shape is None:
        return None
    if isinstance(shape, Sphere):
        return {"kind": "sphere", "center": json_array(shape.center), "radius": float(shape.radius)}
    if isinstance(shape, Ellipsoid):
        return {"kind": "ellipsoid", "center": json_array(shape.center), "radii": json_array(shape.radii),
                "rotation": json_array(shape.rotation)}
    if isinstance(shape, FieldValues):
        return {"kind": "values", "points": json_array(shape.points), "h": json_array(shape.h), "g": json_array(shape.g)}
    raise ValueError(f"shape must be a models.Sphere, a models.Ellipsoid, a FieldValues or None to be logged, "
                     f"got {type(shape).__name__}")


def shape_from_json(d, name: str = "shape"):
    """The Sphere, Ellipsoid or FieldValues of a shape_to_json dict (None for None); ValueError naming `name`."""
    if d is None:
        return None
    if not isinstance(d, dict) or d.get("kind") not in ("sphere", "ellipsoid", "values"):
        raise ValueError(f"{name} must be a sphere, ellipsoid or values record, got {str(d)[:60]}")
    try:
        if d["kind"] == "values":
            return FieldValues(array_from_json(d["points"], f"{name}.points"), array_from_json(d["h"], f"{name}.h"),
                               array_from_json(d["g"], f"{name}.g"))
        if d["kind"] == "sphere":
            return Sphere(array_from_json(d["center"], f"{name}.center"), number_from_json(d["radius"], f"{name}.radius"))
        return Ellipsoid(array_from_json(d["center"], f"{name}.center"), array_from_json(d["radii"], f"{name}.radii"),
                         array_from_json(d["rotation"], f"{name}.rotation"))
    except KeyError as exc:
        raise ValueError(f"{name} lacks the field {exc.args[0]!r}") from None


def inputs_to_json(x: FilterInputs) -> dict:
    """Every field of `x`, enough to rebuild it bit for bit with inputs_from_json."""
    if _UNKNOWN_INPUT_FIELDS:
        raise ValueError(f"FilterInputs has fields the log format does not know: {_UNKNOWN_INPUT_FIELDS}")
    d = {name: json_number(getattr(x, name)) for name in _SCALARS}
    d.update({name: json_array(getattr(x, name)) for name in _ARRAYS})
    d.update({name: None if getattr(x, name) is None else json_array(getattr(x, name)) for name in _OPTIONAL_ARRAYS})
    d.update({name: str(getattr(x, name)) for name in _STRINGS})
    for name in _POINT_LISTS:
        d[name] = [{"name": p.name, "p_W": json_array(p.p_W), "J_W": json_array(p.J_W), "trusted": bool(p.trusted),
                    "margin_mm": json_number(p.margin_mm)} for p in getattr(x, name)]
    for name in _SHAPES:
        try:
            d[name] = shape_to_json(getattr(x, name))
        except ValueError as exc:
            raise ValueError(f"FilterInputs.{name}: {exc}") from None
    return d


def inputs_from_json(d) -> FilterInputs:
    """The FilterInputs of an inputs_to_json dict; ValueError naming the bad field."""
    if not isinstance(d, dict):
        raise ValueError(f"filter inputs must be a JSON object, got {type(d).__name__}")
    missing = [n for n in _SCALARS + _ARRAYS + _OPTIONAL_ARRAYS + _STRINGS + _POINT_LISTS + _SHAPES
               if n not in d and n not in _OPTIONAL_ON_READ]
    if missing:
        raise ValueError(f"filter inputs lack the fields {missing}")
    kw = {name: number_from_json(d[name], name) for name in _SCALARS}
    kw.update({name: array_from_json(d[name], name) for name in _ARRAYS})
    kw.update({name: None if d.get(name) is None else array_from_json(d[name], name) for name in _OPTIONAL_ARRAYS})
    for name in _STRINGS:
        if not isinstance(d.get(name, ""), str):
            raise ValueError(f"{name} must be a string, got {type(d[name]).__name__}")
        kw[name] = d.get(name, "")
    for name in _POINT_LISTS:
        if not isinstance(d[name], list) or not all(isinstance(p, dict) and {"name", "p_W", "J_W"} <= p.keys() for p in d[name]):
            raise ValueError(f"{name} must be a list of {{name, p_W, J_W}} records")
        kw[name] = [PointKinematics(str(p["name"]), array_from_json(p["p_W"], f"{name}.p_W"),
                                    array_from_json(p["J_W"], f"{name}.J_W"), bool(p.get("trusted", True)),
                                    number_from_json(p.get("margin_mm", 0.0), f"{name}.margin_mm"))
                    for p in d[name]]
    for name in _SHAPES:
        kw[name] = shape_from_json(d.get(name), name)
    return FilterInputs(**kw)


def config_to_json(config: FilterConfig) -> dict:
    """The filter configuration's fields (numbers as json_number, the solver name)."""
    return {k: v if isinstance(v, str) else json_number(v) for k, v in dataclasses.asdict(config).items()}


def config_from_json(d) -> FilterConfig:
    """The FilterConfig of a config_to_json dict; ValueError on unknown or bad fields."""
    if not isinstance(d, dict):
        raise ValueError(f"filter config must be a JSON object, got {type(d).__name__}")
    known = {f.name: f for f in dataclasses.fields(FilterConfig)}
    unknown = sorted(set(d) - set(known))
    if unknown:
        raise ValueError(f"filter config has unknown fields {unknown} (logged by another version?)")
    kw = {k: v if isinstance(known[k].default, str) else number_from_json(v, f"config.{k}") for k, v in d.items()}
    for k in ("calibration_bound_mm", "calibration_bound_deg"):  # a config without them kept no calibration bound
        kw.setdefault(k, 0.0)
    return FilterConfig(**kw)
