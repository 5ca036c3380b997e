"""The surgery scenario: placement, trocar and tip-target checks, eye visuals consistent with the ground truth."""
from __future__ import annotations

import xml.etree.ElementTree as ET
from importlib.resources import files

import numpy as np
import pytest

from models.eyes import EMMETROPIC_RADII_MM
from planning.robot import Robot
from planning.scenario import LENS_CENTER_E_MM, LENS_RADII_MM, SurgeryScenario


@pytest.fixture(scope="module")
def scenario():
    return SurgeryScenario()


def test_eye_sdf_shows_the_ground_truth_retina_and_lens():
    sdf = ET.parse(files("planning") / "data" / "eye.sdf").getroot()
    radii = {v.get("name"): np.array(v.find("geometry/ellipsoid/radii").text.split(), float) * 1e3 for v in sdf.iter("visual")}
    np.testing.assert_allclose(radii["retina"], EMMETROPIC_RADII_MM, atol=1e-9)
    np.testing.assert_allclose(radii["lens_keepout"], LENS_RADII_MM, atol=1e-9)


def test_trocar_and_eye_frames_in_the_plant_match_the_scenario(scenario):
    robot = Robot(scenario)
    q = np.zeros(6)
    np.testing.assert_allclose(robot.pose("C", q)[1], scenario.p_WC, atol=1e-9)
    R_WE, p_WE = robot.pose("E", q)
    np.testing.assert_allclose(p_WE, scenario.eye_pose.p_WE, atol=1e-9)
    np.testing.assert_allclose(R_WE, scenario.eye_pose.R_WE, atol=1e-12)
    # the trocar is in the wall: within 1 mm of the retina; the lens sits at z_E = 7.8 mm
    assert abs(scenario.eye.signed_distance(scenario.p_WC)[0]) < 1.0
    np.testing.assert_allclose(scenario.lens_W.center, scenario.eye_pose.to_W(np.array([LENS_CENTER_E_MM]))[0])


def test_true_sensor_differs_from_nominal_by_the_calibration_error(scenario):
    robot = Robot(scenario)
    q = np.array([0.1, 0.3, -0.2, 0.4, 0.5, -0.3])
    p_nom, u_nom = robot.beam(q)
    p_true, u_true = robot.beam(q, true=True)
    assert np.linalg.norm(p_true - p_nom) == pytest.approx(np.linalg.norm(scenario.sensor_offset_S_mm), abs=1e-9)
    assert np.degrees(np.arccos(u_true @ u_nom)) == pytest.approx(np.degrees(np.linalg.norm(scenario.sensor_rotvec_S_rad)), abs=1e-6)
    np.testing.assert_allclose(u_nom, robot.shaft(q)[1], atol=1e-12)  # the beam runs along the shaft


def test_spiral_beams_reach_the_posterior_retina(scenario):
    P_W = scenario.tip_targets_W(scenario.spiral_E()[::50])
    u = P_W - scenario.p_WC
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    hits = P_W + scenario.eye.ray_cast(P_W, u)[:, None] * u
    assert np.all(scenario.eye_pose.to_E(hits)[:, 2] < 0.0)  # behind the equator


def test_peripheral_band_targets_clear_the_lens_and_lie_in_the_band(scenario):
    band = scenario.peripheral_band_E()
    assert len(band) > 40
    assert np.all(scenario.lens_clearance_mm(band) >= 0.5)
    assert np.all((band[:, 2] >= 0.0) & (band[:, 2] <= 5.0 + 1e-9))
    scenario.tip_targets_W(band)  # inside the eye with clearance


def test_bad_trocar_and_tip_targets_are_refused(scenario):
    with pytest.raises(ValueError, match="p_EC.*outside the eye wall"):
        SurgeryScenario(p_EC=[14.0, 0.0, 7.2])
    with pytest.raises(ValueError, match="p_EC.*not in the wall"):
        SurgeryScenario(p_EC=[0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="p_EC"):
        SurgeryScenario(p_EC=[np.nan, 0.0, 7.2])
    with pytest.raises(ValueError, match="tip target 1 .*outside the eye"):
        scenario.tip_targets_W([[0.0, 0.0, 0.0], [0.0, 0.0, -10.5]])
    with pytest.raises(ValueError, match="lens keep-out"):
        scenario.tip_targets_W([[-9.0, 0.0, 5.0]])  # straight through the lens from the trocar
    with pytest.raises(ValueError, match="P_ET"):
        scenario.tip_targets_W([[np.nan, 0.0, 0.0]])


def test_the_scenario_builds_its_true_eye_with_the_shape_parameters_it_is_given():
    u = np.array([[0.0, -np.sin(np.radians(25.0)), -np.cos(np.radians(25.0))]])
    default = SurgeryScenario(eye_name="detached", eye_params={"angle_deg": 25.0})
    high = SurgeryScenario(eye_name="detached", eye_params={"height_mm": 3.0, "angle_deg": 25.0})
    p_E = [s.eye_pose.to_E(s.eye.surface_points(u))[0] for s in (default, high)]
    # the detachment's centre lifts by height_mm: 3.0 mm against the default 2.0 mm
    assert np.linalg.norm(p_E[0]) - np.linalg.norm(p_E[1]) == pytest.approx(1.0, abs=1e-9)
