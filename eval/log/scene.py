"""Foxglove's well-known messages of the run log, built with the foxglove-sdk message
classes (protobuf, Foxglove's published schemas): the frames ("/tf",
foxglove.FrameTransforms), the 3D scene ("/scene", foxglove.SceneUpdate) and run events
("/log", foxglove.Log).

Geometry arrives in mm (W frame) and leaves in metres, as Foxglove's 3D panel expects.
`ns` arguments are log times: the run's wall-clock start + the simulation time, in ns.
"""
from __future__ import annotations

import math

import numpy as np
from foxglove.messages import (
    Color,
    Duration,
    FrameTransform,
    FrameTransforms,
    KeyValuePair,
    LinePrimitive,
    LinePrimitiveLineType,
    Log,
    LogLevel,
    PointCloud,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    SceneUpdate,
    SpherePrimitive,
    Timestamp,
    Vector3,
)

M_PER_MM = 1e-3  # Foxglove's 3D panel works in metres
# topic -> the foxglove-sdk message class logged on it
MESSAGES = {"/tf": FrameTransforms, "/scene": SceneUpdate, "/log": Log, "/oct/points": PointCloud}
LOG_LEVELS = {"debug": LogLevel.Debug, "info": LogLevel.Info, "warning": LogLevel.Warning, "error": LogLevel.Error}
EYE_MODEL_COLOR = {"sphere": (1.0, 0.55, 0.1, 0.25), "ellipsoid": (0.1, 0.8, 0.9, 0.25)}
LENS_COLOR, BEAM_COLOR, TROCAR_COLOR = (0.3, 0.3, 1.0, 0.3), (1.0, 0.0, 0.0, 1.0), (1.0, 0.9, 0.0, 1.0)
BOUNDARY_COLOR = (1.0, 0.2, 0.2, 0.15)


def quaternion_xyzw(R) -> list[float]:
    """Unit quaternion [x, y, z, w] (w >= 0) of the rotation matrix R (3, 3) (on Python
    floats: a scene converts a few dozen frames 20 times a simulated second)."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = np.asarray(R, dtype=float).tolist()
    tr = r00 + r11 + r22
    if tr > 0.0:  # the branch with the largest component keeps the division well conditioned
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [(r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s, 0.25 * s]
    else:
        M = ((r00, r01, r02), (r10, r11, r12), (r20, r21, r22))
        i = 0 if r00 >= r11 and r00 >= r22 else (1 if r11 >= r22 else 2)
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + M[i][i] - M[j][j] - M[k][k])
        q = [0.0, 0.0, 0.0, (M[k][j] - M[j][k]) / s]
        q[i], q[j], q[k] = 0.25 * s, (M[j][i] + M[i][j]) / s, (M[k][i] + M[i][k]) / s
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    sign = 1.0 if q[3] >= 0 else -1.0
    return [sign * v / n for v in q]


def timestamp(ns: int) -> Timestamp:
    return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def _vec(p_mm) -> Vector3:
    x, y, z = (float(v) * M_PER_MM for v in p_mm)
    return Vector3(x=x, y=y, z=z)


def _point(p_mm) -> Point3:
    x, y, z = (float(v) * M_PER_MM for v in p_mm)
    return Point3(x=x, y=y, z=z)


def _quat(R) -> Quaternion:
    x, y, z, w = quaternion_xyzw(R)
    return Quaternion(x=x, y=y, z=z, w=w)


def _pose(p_mm, R=None) -> Pose:
    return Pose(position=_vec(p_mm), orientation=_quat(np.eye(3) if R is None else R))


def _color(rgba) -> Color:
    r, g, b, a = rgba
    return Color(r=r, g=g, b=b, a=a)


def _sphere(shape, rgba) -> SpherePrimitive:
    """A sphere primitive (an ellipsoid when the sizes differ; size = diameters) of a
    models Sphere or Ellipsoid."""
    radii = np.full(3, shape.radius) if hasattr(shape, "radius") else shape.radii
    return SpherePrimitive(pose=_pose(shape.center, getattr(shape, "rotation", None)), size=_vec(2.0 * np.asarray(radii)),
                           color=_color(rgba))


def frame_transforms(ns: int, X_W: dict) -> FrameTransforms:
    """The poses X_WA (4, 4) homogeneous, mm, of frames A in W, at log time ns."""
    stamp = timestamp(ns)
    transforms = []
    for name, X in X_W.items():
        X = np.asarray(X, dtype=float)
        if X.shape != (4, 4) or not np.all(np.isfinite(X)):
            raise ValueError(f"X_W[{name!r}] must be a finite (4, 4) pose, got shape {X.shape}")
        transforms.append(FrameTransform(timestamp=stamp, parent_frame_id="W", child_frame_id=str(name),
                                         translation=_vec(X[:3, 3]), rotation=_quat(X[:3, :3])))
    return FrameTransforms(transforms=transforms)


def scene_update(ns: int, t_s: float, eye=None, beam=None, p_W_trocar=None, lens=None, boundary=None,
                 extra=()) -> SceneUpdate:
    """The 3D scene in W at log time ns (simulation time t_s, s, in each entity's metadata
    'sim_time_s'): the eye model `eye` (Sphere/Ellipsoid, translucent), the boundary the
    filter keeps (`boundary`, a Sphere/Ellipsoid), the lens keep-out `lens`, the OCT `beam`
    as (p_W_start, p_W_end) mm, the trocar point (mm), and `extra` entities (the robot's)."""
    stamp, meta = timestamp(ns), [KeyValuePair(key="sim_time_s", value=repr(float(t_s)))]

    def entity(id_: str, spheres=(), lines=()) -> SceneEntity:
        return SceneEntity(timestamp=stamp, frame_id="W", id=id_, lifetime=Duration(sec=0, nsec=0), frame_locked=False,
                           metadata=meta, spheres=list(spheres), lines=list(lines))

    entities = []
    if eye is not None:
        kind = "sphere" if hasattr(eye, "radius") else "ellipsoid"
        entities.append(entity("eye_model", spheres=[_sphere(eye, EYE_MODEL_COLOR[kind])]))
    if boundary is not None:
        entities.append(entity("boundary", spheres=[_sphere(boundary, BOUNDARY_COLOR)]))
    if lens is not None:
        entities.append(entity("lens", spheres=[_sphere(lens, LENS_COLOR)]))
    if beam is not None:
        line = LinePrimitive(type=LinePrimitiveLineType.LineStrip, pose=_pose(np.zeros(3)), thickness=2.0,
                             scale_invariant=True, points=[_point(beam[0]), _point(beam[1])], color=_color(BEAM_COLOR))
        entities.append(entity("beam", lines=[line]))
    if p_W_trocar is not None:
        trocar = SpherePrimitive(pose=_pose(p_W_trocar), size=_vec(np.full(3, 1.0)), color=_color(TROCAR_COLOR))
        entities.append(entity("trocar", spheres=[trocar]))
    return SceneUpdate(deletions=[], entities=entities + list(extra))


def log_message(ns: int, text: str, level: str = "info", name: str = "vitreoguard") -> Log:
    """A foxglove.Log of `text` at `level` (one of LOG_LEVELS) at log time ns."""
    if level not in LOG_LEVELS:
        raise ValueError(f"level must be one of {sorted(LOG_LEVELS)}, got {level!r}")
    return Log(timestamp=timestamp(ns), level=LOG_LEVELS[level], message=str(text), name=name)
