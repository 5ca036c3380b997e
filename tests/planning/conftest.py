"""Shared fixture: the surgery scenario, its robot, and an RCM posture with the tip at
(1, 2, -3) mm in the eye frame (behind the centre, mid-vitreous)."""
from __future__ import annotations

import numpy as np
import pytest

from planning import Robot, SurgeryScenario, start_posture


@pytest.fixture(scope="module")
def setup():
    scenario = SurgeryScenario()
    robot = Robot(scenario)
    p = scenario.eye_pose.to_W(np.array([[1.0, 2.0, -3.0]]))[0]
    return scenario, robot, start_posture(robot, p, scenario.p_WC)
