"""Meshcat view of a scan: robot, instrument, eye, trocar and the tip path, replayable."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from pydrake.geometry import Meshcat, MeshcatVisualizer, Rgba
from pydrake.systems.framework import DiagramBuilder

from planning.robot import MM_PER_M, Robot


class VisualScene(NamedTuple):
    """A visual copy of a robot's scene wired to Meshcat: publish a posture with `show(q, t)`."""

    diagram: object
    context: object
    plant_context: object
    scene: Robot
    visualizer: MeshcatVisualizer

    def show(self, q, t_s: float) -> None:
        """Publish the robot at joint angles q (6,) rad at time t_s (s)."""
        self.context.SetTime(t_s)
        self.scene.plant.SetPositions(self.plant_context, q)
        self.diagram.ForcedPublish(self.context)


def visual_scene(robot: Robot, meshcat: Meshcat) -> VisualScene:
    """A Robot with `robot`'s scenario in its own diagram, with a MeshcatVisualizer, so that
    `robot`'s diagram stays untouched."""
    builder = DiagramBuilder()
    scene = Robot(robot.scenario, builder)
    vis = MeshcatVisualizer.AddToBuilder(builder, scene.scene_graph, meshcat)
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    return VisualScene(diagram, context, scene.plant.GetMyContextFromRoot(context), scene, vis)


def show_scan(robot: Robot, run, P_WT, meshcat: Meshcat | None = None, fps: float = 30.0) -> str:
    """Publish a recording of the scan `run` (planning.scan.ScanRun) and the tip targets
    P_WT (N, 3) mm as a line; returns the Meshcat URL."""
    meshcat = Meshcat() if meshcat is None else meshcat
    view = visual_scene(robot, meshcat)
    meshcat.SetLine("tip_path", np.asarray(P_WT, dtype=float).T / MM_PER_M, 1.0, Rgba(0.9, 0.1, 0.1, 1.0))
    view.visualizer.StartRecording()
    for t in np.arange(run.t[0], run.t[-1], 1.0 / fps):
        view.show(run.q[min(np.searchsorted(run.t, t), len(run.t) - 1)], t)
    view.visualizer.StopRecording()
    view.visualizer.PublishRecording()
    return meshcat.web_url()
