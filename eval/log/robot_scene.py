"""The robot and the measured points in Foxglove's 3D panel: each link's visual geometry
(from the plant's scene graph: the URDF's boxes and cylinders, the instrument's holder
and shaft) as scene entities locked to the link's frame, the links' poses as frame
transforms, and the iiOCT's measured retinal points as foxglove.PointCloud.
Geometry arrives in mm (W) and leaves in metres; `ns` arguments are log times.
"""
from __future__ import annotations

import numpy as np
from foxglove.messages import (
    CubePrimitive,
    CylinderPrimitive,
    Duration,
    PackedElementField,
    PackedElementFieldNumericType,
    PointCloud,
    SceneEntity,
)
from pydrake.geometry import Box, Cylinder, Role
from pydrake.geometry import Sphere as DrakeSphere
from pydrake.multibody.tree import BodyIndex

from eval.log.scene import M_PER_MM, _color, _pose, _vec, timestamp
from models import Ellipsoid, Sphere

LINK_COLOR = (0.75, 0.75, 0.78, 1.0)
INSTRUMENT_COLOR = (0.9, 0.9, 0.2, 1.0)
POINTS_FIELDS = [PackedElementField(name=n, offset=4 * k, type=PackedElementFieldNumericType.Float32)
                 for k, n in enumerate("xyz")]
MM_PER_M = 1e3


class RobotScene:
    """The links of `robot` (planning.Robot) that carry visual geometry: `entities(ns)` the
    scene entities (once per frame id, locked to it), `link_poses(q)` the links' X_WL (4, 4) mm."""

    def __init__(self, robot):
        plant, inspector = robot.plant, robot.scene_graph.model_inspector()
        self._plant, self._context = plant, plant.CreateDefaultContext()
        arm = plant.GetBodyByName("base").model_instance()
        self.links = []  # (name, body, [(kind, size mm (3,), R_LG, p_LG mm)])
        for i in range(plant.num_bodies()):
            body = plant.get_body(BodyIndex(i))
            frame = plant.GetBodyFrameIdIfExists(body.index())
            if body.model_instance() != arm or frame is None:
                continue
            parts = [self._part(inspector.GetShape(g), inspector.GetPoseInFrame(g))
                     for g in inspector.GetGeometries(frame, Role.kIllustration)]
            parts = [p for p in parts if p is not None]
            if parts:
                self.links.append((body.name(), body, parts))
        self._primitives = None  # per link (cubes, cylinders): the same in every scene (entities)

    @staticmethod
    def _part(shape, X_LG):
        """(kind, size mm: Foxglove's box sizes or cylinder diameters and length, R_LG, p_LG mm)."""
        R, p = X_LG.rotation().matrix(), MM_PER_M * X_LG.translation()
        if isinstance(shape, Box):
            return "cube", MM_PER_M * np.array([shape.width(), shape.depth(), shape.height()]), R, p
        if isinstance(shape, Cylinder):
            d = 2.0 * MM_PER_M * shape.radius()
            return "cylinder", np.array([d, d, MM_PER_M * shape.length()]), R, p
        if isinstance(shape, DrakeSphere):
            return "sphere", np.full(3, 2.0 * MM_PER_M * shape.radius()), R, p
        return None

    def link_poses(self, q) -> dict:
        """{link name: X_WL (4, 4), mm} at joint angles q (6,) rad."""
        self._plant.SetPositions(self._context, np.asarray(q, dtype=float))
        out = {}
        for name, body, _ in self.links:
            X = self._plant.EvalBodyPoseInWorld(self._context, body)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = X.rotation().matrix(), MM_PER_M * X.translation()
            out[name] = T
        return out

    def entities(self, ns: int) -> list:
        """One SceneEntity per link ('robot/<link>'), in the link's frame, frame-locked."""
        if self._primitives is None:
            self._primitives = [self._link_primitives(name, parts) for name, _, parts in self.links]
        stamp = timestamp(ns)
        return [SceneEntity(timestamp=stamp, frame_id=name, id=f"robot/{name}", lifetime=Duration(sec=0, nsec=0),
                            frame_locked=True, cubes=cubes, cylinders=cylinders)
                for (name, _, _), (cubes, cylinders) in zip(self.links, self._primitives)]

    @staticmethod
    def _link_primitives(name: str, parts) -> tuple[list, list]:
        """(cubes, cylinders) of a link's parts, in its frame."""
        color = _color(INSTRUMENT_COLOR if name == "instrument" else LINK_COLOR)
        cubes = [CubePrimitive(pose=_pose(p, R), size=_vec(size), color=color) for kind, size, R, p in parts
                 if kind == "cube"]
        cylinders = [CylinderPrimitive(pose=_pose(p, R), size=_vec(size), bottom_scale=1.0, top_scale=1.0, color=color)
                     for kind, size, R, p in parts if kind == "cylinder"]
        return cubes, cylinders


def point_cloud(ns: int, P_W) -> PointCloud:
    """The points P_W (N, 3) mm as a foxglove.PointCloud in W (float32 x, y, z in metres)."""
    P = np.ascontiguousarray(M_PER_MM * np.asarray(P_W, dtype=float).reshape(-1, 3), dtype="<f4")
    return PointCloud(timestamp=timestamp(ns), frame_id="W", pose=_pose(np.zeros(3)), point_stride=12,
                      fields=POINTS_FIELDS, data=P.tobytes())


def shrunk(shape, by_mm: float):
    """The Sphere or Ellipsoid `shape` with its radii `by_mm` smaller (at least 0.1 mm): the
    boundary the filter keeps inside a model, for display (for a sphere exactly; an
    ellipsoid's inner parallel surface is not an ellipsoid, this one approximates it)."""
    if isinstance(shape, Sphere):
        return Sphere(shape.center, max(shape.radius - by_mm, 0.1))
    return Ellipsoid(shape.center, np.maximum(shape.radii - by_mm, 0.1), shape.rotation)
