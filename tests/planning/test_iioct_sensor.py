"""The iiOCT sensor on the robot: true beam on the true eye, point from the reported
angles and the calibrated pose; distance mode = the full chain's statistics; the Drake
block with packets, time offset and bad joint states."""
from __future__ import annotations

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, DiscreteTimeIntegrator

from planning.iioct_sensor import IioctSensor, IioctSensorSystem, extractor_error_model


def test_the_beam_comes_from_the_true_sensor_and_the_point_from_the_calibrated_one(setup):
    scenario, robot, q = setup
    s = IioctSensor(robot, mode="distance", seed=1)
    sample = s.sample(q, q, 0.0)
    assert sample.valid and sample.reason == ""
    o_true, u_true = robot.beam(q, true=True)
    d_true = scenario.eye.ray_cast(o_true[None], u_true[None])[0]
    assert abs(sample.distance_mm - d_true) < 0.1  # extractor error at normal incidence: tens of um
    o, u = robot.beam(q)
    np.testing.assert_allclose(sample.p_W, o + sample.distance_mm * u, atol=1e-12)
    # the point misses the true hit by about the calibration error (20 um, 0.1 deg over ~8 mm: ~25 um)
    assert np.linalg.norm(sample.p_W - (o_true + d_true * u_true)) < 0.1


def test_a_wrong_calibration_shifts_the_points_as_predicted(setup):
    scenario, robot, q = setup
    offset = np.array([0.1, -0.05, 0.0])  # mm, in S
    a = IioctSensor(robot, mode="distance", seed=4).sample(q, q, 0.0)
    b = IioctSensor(robot, mode="distance", seed=4, X_S_Scal=(np.eye(3), offset)).sample(q, q, 0.0)
    R_WS, _ = robot.pose("S", q)
    np.testing.assert_allclose(b.p_W - a.p_W, R_WS @ offset, atol=1e-12)


def test_distance_mode_matches_the_full_chain_statistically(setup):
    """Same geometry, 150 samples each: bias within 10 um and SD within a factor 2 (the
    error model is tabulated from the extractor with 24 scans per cell); valid counts
    within 4 binomial SDs below the tabulated invalid fraction's expectation (at this
    beam, ~7.7 mm at ~19 deg: p_invalid ~7 %, 139 +- 3 valid)."""
    scenario, robot, q = setup
    n, stats = 150, {}
    for mode in ("ascan", "distance"):
        s = IioctSensor(robot, mode=mode, seed=7)
        d = np.array([x.distance_mm for x in s.samples([q] * n, [q] * n, np.arange(n) * 5e-4) if x.valid])
        stats[mode] = (np.median(d), np.std(d), len(d))
    assert abs(stats["ascan"][0] - stats["distance"][0]) < 0.010
    assert 0.5 < stats["distance"][1] / stats["ascan"][1] < 2.0
    p = extractor_error_model().interpolate(*s.true_geometry(np.array([q])))[0, 0]
    assert stats["ascan"][2] >= n * (1 - p) - 4 * np.sqrt(n * p * (1 - p))
    assert stats["distance"][2] >= n * (1 - p) - 4 * np.sqrt(n * p * (1 - p))


def test_the_error_model_is_tabulated_from_the_extractor():
    m = extractor_error_model()
    normal = [m.bias[i][0] for i in range(len(m.distances_mm))]
    assert max(abs(b) for b in normal) <= 0.005  # issue 5: |bias| <= 5 um at normal incidence
    assert max(m.sd[i][0] for i in range(len(m.distances_mm))) <= 0.020  # SD <= 20 um
    assert m.p_invalid[-1][-1] > 0.5  # 25 mm at 75 deg: mostly invalid


def test_encoder_noise_scatters_the_points(setup):
    scenario, robot, q = setup
    quiet = IioctSensor(robot, mode="distance", seed=2)
    noisy = IioctSensor(robot, mode="distance", seed=2, encoder_noise_rad=1e-4)
    P = [np.array([s.p_W for s in sensor.samples([q] * 100, [q] * 100, np.arange(100) * 5e-4)]) for sensor in (quiet, noisy)]
    # 1e-4 rad on joints 160-300 mm from the tip moves the point by tens of um laterally
    assert np.linalg.norm(np.nanstd(P[1], axis=0)) > 3 * np.linalg.norm(np.nanstd(P[0], axis=0))


def test_bad_joint_angles_give_an_invalid_sample_never_a_point(setup):
    scenario, robot, q = setup
    s = IioctSensor(robot, mode="distance")
    bad = s.sample(np.full(6, np.nan), q, 0.0)
    assert not bad.valid and bad.reason.startswith("bad_joint_state") and np.all(np.isnan(bad.p_W))
    with pytest.raises(ValueError, match="mode"):
        IioctSensor(robot, mode="video")
    with pytest.raises(ValueError, match="encoder_noise_rad"):
        IioctSensor(robot, encoder_noise_rad=-1.0)


def _moving_diagram(robot, q0, qdot, offset_s):
    """q(t) = q0 + t qdot into the sensor block; returns (simulator, sensor system)."""
    b = DiagramBuilder()
    src = b.AddSystem(ConstantVectorSource(qdot))
    integ = b.AddSystem(DiscreteTimeIntegrator(6, 5e-4))
    sensor = b.AddSystem(IioctSensorSystem(IioctSensor(robot, mode="distance", seed=0), 2000.0, offset_s, packet=10))
    b.Connect(src.get_output_port(), integ.get_input_port())
    b.Connect(integ.get_output_port(), sensor.GetInputPort("q"))
    d = b.Build()
    sim = Simulator(d)
    integ.set_integral_value(integ.GetMyMutableContextFromRoot(sim.get_mutable_context()), q0)
    return sim, sensor


def test_the_block_samples_at_2_khz_in_packets_and_the_time_offset_moves_the_points(setup):
    scenario, robot, q = setup
    qdot = np.array([0.05, 0.0, 0.0, 0.0, 0.0, 0.0])  # rad/s
    out = {}
    for offset in (0.0, 0.002):
        sim, sensor = _moving_diagram(robot, q, qdot, offset)
        sim.AdvanceTo(0.0101)
        ctx = sensor.GetMyContextFromRoot(sim.get_context())
        packet = sensor.GetOutputPort("samples").Eval(ctx)
        m = sensor.GetOutputPort("measurement").Eval(ctx)
        assert len(packet) == 10 and np.allclose(np.diff([s.t_s for s in packet]), 5e-4)
        assert m[3] == packet[-1].t_s and m[1] == 1.0
        out[offset] = packet[-1]
    # with the offset the beam is taken 2 ms earlier: the origin lags by |v_origin| x 2 ms
    o_then, _ = robot.beam(q + (out[0.0].t_s - 0.002) * qdot)
    np.testing.assert_allclose(out[0.002].beam_origin_W, o_then, atol=1e-9)
    lag = np.linalg.norm(out[0.002].beam_origin_W - out[0.0].beam_origin_W)
    v = np.linalg.norm(robot.jacobian("S", np.zeros(3), q) @ qdot)
    assert abs(lag - v * 0.002) < 0.05 * v * 0.002
