"""The OCT-robot time offset from the synchronisation motion."""
import numpy as np
import pytest

from planning.clock_sync import (SyncError, estimate_time_offset, find_sync_segment, sync_axial_mm,
                                 sync_joint_path)


def _streams(offset_s, rng, noise_mm=0.01, duration_s=3.0):
    """The robot's travel at 1 kHz (robot clock) and the OCT distance at 2 kHz (OCT clock,
    offset_s later), the distance 12 mm minus the travel, with extraction noise."""
    t_robot = np.arange(0.0, duration_s + 1e-9, 1e-3)
    s = sync_axial_mm(t_robot, duration_s=duration_s) + 2e-3 * rng.standard_normal(len(t_robot))  # encoder noise
    t_true = np.arange(0.0, duration_s, 5e-4)
    d = 12.0 - sync_axial_mm(t_true, duration_s=duration_s) + noise_mm * rng.standard_normal(len(t_true))
    return t_true + offset_s, d, t_robot, s


@pytest.mark.parametrize("offset_ms", [-10.0, -3.3, 0.0, 0.26, 7.7, 10.0])
def test_the_offset_is_recovered_within_half_a_millisecond(offset_ms):
    # the target: 0.5 ms over [-10, 10] ms (the paper: 2.6 ms); 10 um extraction noise
    est = estimate_time_offset(*_streams(1e-3 * offset_ms, np.random.default_rng(3)))
    assert abs(1e3 * est.offset_s - offset_ms) < 0.5
    assert est.gain == pytest.approx(-1.0, abs=0.01)
    assert est.residual_rms_mm == pytest.approx(0.01, rel=0.3)


def test_an_amplitude_modulated_sinusoid_has_one_minimum():
    # a plain sinusoid would match again one period (500 ms) on: the envelope tells them apart
    est = estimate_time_offset(*_streams(0.004, np.random.default_rng(4)), max_offset_s=0.6)
    assert abs(est.offset_s - 0.004) < 5e-4


def test_a_distance_that_ignores_the_motion_is_refused():
    t_oct, d, t_robot, s = _streams(0.0, np.random.default_rng(5))
    with pytest.raises(SyncError, match="does not follow"):
        estimate_time_offset(t_oct, np.full_like(d, 12.0) + 0.01 * np.random.default_rng(6).standard_normal(len(d)),
                             t_robot, s)


def _beams(travel_mm, lateral_mm):
    """Beam origins moving by travel (along z) and lateral (along x), direction +z."""
    O = np.column_stack([lateral_mm, np.zeros_like(travel_mm), travel_mm])
    return O, np.tile([0.0, 0.0, 1.0], (len(O), 1))


def test_the_segment_is_the_in_and_out_motion_before_the_scan():
    t = np.arange(0.0, 3.0, 1e-3)
    scan = np.linspace(0.0, 5.0, 2000)  # then the tip moves sideways
    O, U = _beams(np.concatenate([sync_axial_mm(t), np.zeros(2000)]), np.concatenate([np.zeros(len(t)), scan]))
    first, stop = find_sync_segment(O, U)
    assert first == 0 and len(t) <= stop < len(t) + 100  # 0.1 mm sideways at 2.5 um per sample: 40 samples


def test_a_recording_without_the_motion_is_refused():
    O, U = _beams(np.zeros(3000), np.linspace(0.0, 5.0, 3000))
    with pytest.raises(SyncError, match="no synchronisation segment"):
        find_sync_segment(O, U)


def test_the_motion_keeps_the_shaft_on_its_line():
    from planning import Robot, SurgeryScenario
    from planning.scan import start_posture

    scenario = SurgeryScenario()
    robot = Robot(scenario)
    P = scenario.eye_pose.to_W(scenario.spiral_E(1.5, 1.0, 0.1))
    q0 = start_posture(robot, P[0], scenario.p_WC)
    t = np.arange(0.0, 3.0, 0.01)
    Q = sync_joint_path(robot, q0, t)
    a = sync_axial_mm(t)
    p0 = robot.point("T", np.zeros(3), q0)
    u0 = robot.pose("F", q0)[0][:, 0]
    for q, ak in zip(Q[::10], a[::10]):
        assert np.allclose(robot.point("T", np.zeros(3), q), p0 + ak * u0, atol=1e-6)
        assert np.allclose(robot.pose("F", q)[0][:, 0], u0, atol=1e-9)
