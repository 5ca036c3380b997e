"""Meshcat view of a scan: robot, instrument, eye, trocar and the tip path, replayable."""
from __future__ import annotations

import numpy as np
from pydrake.geometry import Meshcat, MeshcatVisualizer, Rgba
from pydrake.systems.framework import DiagramBuilder

from planning.robot import MM_PER_M, Robot


def show_scan(robot: Robot, run, P_WT, meshcat: Meshcat | None = None, fps: float = 30.0) -> str:
    """Publish a recording of the scan `run` (planning.scan.ScanRun) and the tip targets
    P_WT (N, 3) mm as a line; returns the Meshcat URL. Builds its own visual copy of the
    scene (a Robot with the same scenario), so `robot`'s diagram stays untouched."""
    meshcat = Meshcat() if meshcat is None else meshcat
    builder = DiagramBuilder()
    scene = Robot(robot.scenario, builder)
    vis = MeshcatVisualizer.AddToBuilder(builder, scene.scene_graph, meshcat)
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    plant_context = scene.plant.GetMyContextFromRoot(context)
    meshcat.SetLine("tip_path", np.asarray(P_WT, dtype=float).T / MM_PER_M, 1.0, Rgba(0.9, 0.1, 0.1, 1.0))
    vis.StartRecording()
    for t in np.arange(run.t[0], run.t[-1], 1.0 / fps):
        context.SetTime(t)
        scene.plant.SetPositions(plant_context, run.q[min(np.searchsorted(run.t, t), len(run.t) - 1)])
        diagram.ForcedPublish(context)
    vis.StopRecording()
    vis.PublishRecording()
    return meshcat.web_url()
