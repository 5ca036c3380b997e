"""Meshcat view of closed-loop runs: robot and instrument, the true retina, the model the
filter used and its boundary (as they changed: prior -> sphere -> ellipsoid), the iiOCT
beam and the tip path, as a recording to replay in the browser."""
from __future__ import annotations

import numpy as np
from pydrake.geometry import Meshcat, Rgba
from pydrake.math import RigidTransform, RotationMatrix

from planning.robot import MM_PER_M, Robot
from planning.view import visual_scene

BEAM_LENGTH_MM = 25.0  # drawn length of the beam (the extractor's working range)
_TRUTH_RGBA = Rgba(0.75, 0.75, 0.75, 0.25)
_MODEL_RGBA = Rgba(0.1, 0.7, 0.2, 0.35)
_BOUNDARY_RGBA = Rgba(0.95, 0.45, 0.1, 0.30)


def direction_grid(n_theta: int = 30, n_phi: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """(unit directions U (n_theta * n_phi, 3), triangles F (M, 3) indexing U) of a
    latitude-longitude grid, poles included as rings, closed in longitude; every triangle
    is counter-clockwise seen from outside."""
    if n_theta < 3 or n_phi < 3:
        raise ValueError(f"direction_grid needs n_theta, n_phi >= 3, got {n_theta}, {n_phi}")
    th = np.linspace(0.0, np.pi, n_theta)
    ph = np.linspace(0.0, 2.0 * np.pi, n_phi, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    U = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], axis=-1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_theta - 1), np.arange(n_phi), indexing="ij")
    a = i * n_phi + j
    b = i * n_phi + (j + 1) % n_phi
    c, d = a + n_phi, b + n_phi
    F = np.concatenate([np.stack([a, c, d], -1).reshape(-1, 3), np.stack([a, d, b], -1).reshape(-1, 3)])
    return U, F


def model_surface_mm(shape, offset_mm: float = 0.0, n_theta: int = 30, n_phi: int = 60):
    """(vertices (N, 3) mm, triangles (M, 3)) of a Sphere or Ellipsoid's surface (its ray
    casts from its centre) moved `offset_mm` inward along its normal (the filter's boundary
    for offset = d_safe + margin; exact, as an offset surface, at every vertex)."""
    U, F = direction_grid(n_theta, n_phi)
    C = np.broadcast_to(shape.center, U.shape)
    V = C + shape.ray_cast(C, U)[:, None] * U
    if offset_mm:
        V = V + offset_mm * shape.gradient(V)  # gradient: unit, towards the inside
    return V, F


def eye_surface_mm(eye, n_theta: int = 40, n_phi: int = 80):
    """(vertices (N, 3) mm in W, triangles) of a ground-truth eye's retina (models.eyes)."""
    U, F = direction_grid(n_theta, n_phi)
    return eye.surface_points(U), F


def _set_mesh(meshcat: Meshcat, path: str, V_mm: np.ndarray, F: np.ndarray, rgba: Rgba) -> None:
    meshcat.SetTriangleMesh(path, np.asfortranarray(V_mm.T / MM_PER_M), np.asfortranarray(F.T.astype(np.int32)), rgba)


def show_loop(robot: Robot, runs: list, margins, d_safe_mm: float, prior, eye=None,
              meshcat: Meshcat | None = None, fps: float = 30.0) -> str:
    """Publish a recording of closed-loop `runs` (eval.closed_loop.LoopRun, played one
    after the other) and return the Meshcat URL. Shown: the robot and instrument, the true
    retina `eye` (models.eyes, if given), for each model the filter used (the runs'
    `model_epochs`) its surface and its boundary d_safe_mm + `margins.margin_mm(kind,
    residual)` inside it (the `prior` Sphere stands for the prior), visible while in use,
    the beam from the nominal sensor pose (drawn BEAM_LENGTH_MM long) and the tip path.
    `robot`'s own diagram stays untouched (planning.view.visual_scene)."""
    if not runs or any(len(r.t) == 0 for r in runs):
        raise ValueError("show_loop needs at least one run, and no empty run")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be > 0, got {fps}")
    meshcat = Meshcat() if meshcat is None else meshcat
    view = visual_scene(robot, meshcat)

    if eye is not None:
        _set_mesh(meshcat, "truth/retina", *eye_surface_mm(eye), _TRUTH_RGBA)
    epochs = []  # (start time on the recording's clock, path)
    t_start, tip_path = 0.0, []
    for k, run in enumerate(runs):
        for e, snap in enumerate(run.model_epochs):
            shape = prior if snap.shape is None else snap.shape
            margin = (0.0 if snap.field is not None or snap.kind == "prior"  # the local model's sigma varies: not drawn
                      else margins.margin_mm(snap.kind, snap.residual_mm))
            path = f"model/{k}_{e}_{snap.kind}"
            _set_mesh(meshcat, f"{path}/surface", *model_surface_mm(shape), _MODEL_RGBA)
            _set_mesh(meshcat, f"{path}/boundary", *model_surface_mm(shape, d_safe_mm + margin), _BOUNDARY_RGBA)
            epochs.append((t_start + max(snap.t_s - run.t[0], 0.0) if e else t_start, path))
        tip_path.append(np.array([robot.pose("T", q)[1] for q in run.q[:: max(len(run.q) // 2000, 1)]]))
        t_start += run.duration_s
    meshcat.SetLine("tip_path", np.asfortranarray(np.vstack(tip_path).T / MM_PER_M), 1.0, Rgba(0.9, 0.1, 0.1, 1.0))
    meshcat.SetLine("beam", np.asfortranarray(np.array([[0.0, 0.0], [0.0, 0.0], [0.0, BEAM_LENGTH_MM / MM_PER_M]])),
                    2.0, Rgba(0.2, 0.4, 1.0, 1.0))

    animation = view.visualizer.StartRecording()
    t_clock, shown = 0.0, None
    for run in runs:
        for t in np.arange(0.0, run.duration_s, 1.0 / fps):
            q = run.q[min(int(np.searchsorted(run.t - run.t[0], t)), len(run.q) - 1)]
            now = t_clock + t
            view.show(q, now)
            frame = animation.frame(now)
            R_WS, p_WS = robot.pose("S", q)
            animation.SetTransform(frame, "/drake/beam", RigidTransform(RotationMatrix(R_WS), p_WS / MM_PER_M))
            current = max((i for i, (t0, _) in enumerate(epochs) if t0 <= now), default=0)
            if current != shown:  # a property holds until set again
                for i, (_, path) in enumerate(epochs):
                    animation.SetProperty(frame, f"/drake/{path}", "visible", i == current)
                shown = current
        t_clock += run.duration_s
    view.visualizer.StopRecording()
    view.visualizer.PublishRecording()
    return meshcat.web_url()
