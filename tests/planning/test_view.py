"""Meshcat view of a scan: the robot follows the recorded joints, the tip path is drawn."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from pydrake.geometry import Meshcat

from planning.view import show_scan, visual_scene


def test_the_scan_recording_has_the_robot_and_the_tip_path(setup):
    scenario, robot, q = setup
    run = SimpleNamespace(t=np.linspace(0.0, 0.5, 11), q=np.tile(q, (11, 1)))
    meshcat = Meshcat()
    url = show_scan(robot, run, scenario.eye_pose.to_W(scenario.spiral_E(revolutions=1.0)), meshcat=meshcat)
    assert url.startswith("http") and meshcat.HasPath("/drake/tip_path")


def test_the_visual_scene_poses_the_robot_like_the_robot_itself(setup):
    _, robot, q = setup
    view = visual_scene(robot, Meshcat())
    view.show(q, 0.0)
    plant = view.scene.plant
    context = plant.GetMyContextFromRoot(view.context)
    np.testing.assert_array_equal(plant.GetPositions(context), q)
    np.testing.assert_allclose(view.scene.pose("T", q)[1], robot.pose("T", q)[1], atol=1e-9)
