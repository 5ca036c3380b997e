"""The phantom scene (planning.phantom): the printed lower half open on the bench, scanned
from above through a pivot in the air, reachable, inside the fibre's range, and the half
turn about the shaft between the two passes."""
from __future__ import annotations

import numpy as np
import pytest

from models.iioct import OctEngine
from models.shapes.rays import incidences_rad
from planning import Robot
from planning.phantom import (PHANTOM_TIP_PLANE_Z_E_MM, START_ROLL_RAD, PhantomScenario, return_pass, rolled,
                              scan_joint_margin_deg)
from planning.scan import start_posture


@pytest.fixture(scope="module")
def bench():
    scenario = PhantomScenario(eye_name="myopic")
    return scenario, Robot(scenario)


def test_the_default_placement_reaches_the_whole_spiral_within_the_joint_limits(bench):
    scenario, robot = bench
    # every joint inside its limits and the wrist beyond 15 deg of its J5 = 0 singularity,
    # on one closed-form branch over the whole spiral (every 1 mm)
    assert scan_joint_margin_deg(robot, scenario) > 0.0


def test_the_beam_sees_the_lower_half_from_above_within_the_fibres_range(bench):
    scenario, robot = bench
    P = scenario.spiral_E(1.5, 6.0, 0.5)
    assert np.allclose(P[:, 2], PHANTOM_TIP_PLANE_Z_E_MM) and PHANTOM_TIP_PLANE_Z_E_MM > 0.0  # above the rim
    U = P - scenario.p_EC
    U /= np.linalg.norm(U, axis=1)[:, None]
    eye = scenario.eye
    P_W, U_W = scenario.eye_pose.to_W(P), U @ scenario.eye_pose.R_WE.T
    d = eye.ray_cast(P_W, U_W)
    hit_E = scenario.eye_pose.to_E(P_W + d[:, None] * U_W)
    assert np.all(np.isfinite(d)) and np.all(hit_E[:, 2] < 0.0)  # the lower half, the phantom's
    assert d.max() < OctEngine().max_distance_mm and d.min() > OctEngine().working_distance_mm
    # the pole to within 10 deg of the rim: the whole lower half
    polar = np.degrees(np.arccos(-hit_E[:, 2] / np.linalg.norm(hit_E, axis=1)))
    assert polar.min() < 1.0 and polar.max() > 80.0
    # below 45 deg of incidence everywhere: the extractor's bias stays under 20 um there
    # (models.iioct.error_model: 55 deg gives 20-120 um)
    inc = np.degrees(incidences_rad(eye.gradient(P_W + d[:, None] * U_W), U_W))
    assert inc.max() < 45.0


def test_a_spiral_wider_than_the_cup_is_refused(bench):
    scenario, _ = bench
    with pytest.raises(ValueError, match="past the rim"):
        scenario.spiral_E(4.0, 6.0, 0.5)  # 24 mm: the beam would pass over the rim


def test_the_half_turn_keeps_the_tip_and_the_shaft_and_flips_the_instrument(bench):
    scenario, robot = bench
    P = scenario.eye_pose.to_W(scenario.spiral_E(3.0, 1.0, 0.1))
    q0 = rolled(start_posture(robot, P[0], scenario.p_WC))
    assert q0[5] == START_ROLL_RAD
    Q = return_pass(robot, P[:40], scenario.p_WC, q0, 15.0, 1000.0)
    turn = Q[:1000]  # ROLL_TURN_S at 1 kHz: J6 alone
    tips = np.array([robot.point("T", np.zeros(3), q) for q in turn[::50]])
    assert np.max(np.linalg.norm(tips - robot.point("T", np.zeros(3), q0), axis=1)) < 1e-9
    assert np.allclose(turn[:, :5], q0[:5]) and turn[-1, 5] == pytest.approx(START_ROLL_RAD + np.pi, abs=1e-12)
    assert np.all(np.abs(Q[:, 5]) <= np.pi)
    # the instrument's y axis turned by 180 deg about the shaft: a lateral sensor error flips
    y0, y1 = robot.pose("I", q0)[0][:, 1], robot.pose("I", turn[-1])[0][:, 1]
    assert y0 @ y1 == pytest.approx(-1.0, abs=1e-9)
    # then the tip comes back to the spiral's start
    assert np.linalg.norm(robot.point("T", np.zeros(3), Q[-1]) - P[0]) < 0.05
