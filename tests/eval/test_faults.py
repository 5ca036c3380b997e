"""The fault classes of `vitreoguard faults`: what each changes, and how stream-fault
detection is timed."""
from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pytest

from eval.closed_loop import LoopConfig
from eval.experiments.boundary import infeasible_stops
from eval.experiments.faults import (
    FAULT_CLASSES, ROBOT_CLASSES, STREAM_CLASSES, detection_ms, fault_class, margin_costs,
)


@pytest.mark.parametrize("name", FAULT_CLASSES)
def test_each_class_changes_only_its_own_error(name):
    base = LoopConfig()
    fc = fault_class(name, base)
    changed = {k for k in ("actuator", "oct_time_offset_s", "encoder_noise_rad", "stream_fault")
               if getattr(fc.campaign, k) != getattr(base, k)}
    expected = {"delay": {"actuator"}, "lag": {"actuator"}, "accel_limit": {"actuator"},
                "time_offset": {"oct_time_offset_s"}, "encoder_noise": {"encoder_noise_rad"},
                "combined": {"actuator", "oct_time_offset_s", "encoder_noise_rad"}}
    expected.update({k: {"stream_fault"} for k in STREAM_CLASSES})
    assert changed == expected.get(name, set())
    if name in STREAM_CLASSES:  # the model is built on a healthy stream
        assert fc.build.stream_fault.kind == "none"
    assert (fc.floater_rate > 0) == (name in ("floaters", "combined"))
    # the ideal class alone keeps no calibration bound in its margin
    assert (fc.campaign.filter.calibration_margin_mm == 0.0) == (name == "ideal")


def test_the_combined_class_is_every_robot_class_at_once_each_as_it_is_alone():
    base = LoopConfig()
    combined = fault_class("combined", base)
    actuator = combined.campaign.actuator
    for name in ROBOT_CLASSES:
        alone = fault_class(name, base)
        for k, v in alone.parameters.items():  # the actuator's: each class names all three (below)
            assert k.startswith("actuator_") or combined.parameters[k] == v
        for k, v in alone.scenario_kwargs.items():
            np.testing.assert_array_equal(combined.scenario_kwargs[k], v)
        for k in ("oct_time_offset_s", "encoder_noise_rad"):
            if getattr(alone.campaign, k) != getattr(base, k):
                assert getattr(combined.campaign, k) == getattr(alone.campaign, k)
        for k in ("delay_s", "lag_s", "accel_limit_rad_s2"):
            if getattr(alone.campaign.actuator, k) != getattr(base.actuator, k):
                assert getattr(actuator, k) == getattr(alone.campaign.actuator, k)
    assert combined.floater_rate == fault_class("floaters", base).floater_rate
    assert actuator.delay_s == 0.005 and actuator.lag_s == 0.020 and np.isfinite(actuator.accel_limit_rad_s2)
    assert (combined.parameters["actuator_delay_ms"], combined.parameters["actuator_lag_ms"]) == (5.0, 20.0)
    assert combined.parameters["actuator_accel_limit_deg_s2"] == fault_class("accel_limit", base).parameters[
        "actuator_accel_limit_deg_s2"]
    assert combined.build is combined.campaign  # the spiral builds the model through the same errors
    assert not set(STREAM_CLASSES) & set(ROBOT_CLASSES)


def test_the_calibration_class_puts_the_true_sensor_behind_by_the_declared_bound():
    base = LoopConfig()
    fc = fault_class("calibration", base)
    # behind its calibrated origin along the beam (S z): every point measured that much too deep
    np.testing.assert_allclose(fc.scenario_kwargs["sensor_offset_S_mm"], [0.0, 0.0, -base.filter.calibration_bound_mm])
    assert np.linalg.norm(fc.scenario_kwargs["sensor_rotvec_S_rad"]) == pytest.approx(
        np.radians(base.filter.calibration_bound_deg))


def test_detection_is_the_first_stale_sensor_stop_after_the_onset():
    t = np.arange(0.0, 0.3, 0.001)
    ok = t < 0.142
    reasons = ["ok" if o else "stale sensor (frozen distances): 0.051 s old > 0.05 s" for o in ok]
    never = SimpleNamespace(t=t, ok=np.ones_like(ok), reasons=["ok"] * len(t))
    d = detection_ms([SimpleNamespace(t=t, ok=ok, reasons=reasons), never], 0.1)
    assert d["max"] == pytest.approx(42.0) and d["undetected"] == 1


def test_margin_costs_are_each_class_minimum_against_the_ideal_ones():
    classes = {"ideal": {"min_true_clearance_mm": 0.55}, "none": {"min_true_clearance_mm": 0.61},
               "lag": {"min_true_clearance_mm": 0.70}, "accel_limit": {"error": "not run"}}
    assert margin_costs(classes) == pytest.approx({"ideal": 0.0, "none": 0.06, "lag": 0.15})
    assert margin_costs({"none": {"min_true_clearance_mm": 0.61}}) == {}


def test_infeasible_stops_count_runs_of_qp_steps_and_those_right_after_an_accepted_step():
    brake, qp = "actuator cannot brake before the boundary", "QP: infeasible or not solved"
    # ok, QP, QP, ok, brake, QP, ok | QP (the run's first step), ok
    a = SimpleNamespace(ok=np.array([1, 0, 0, 1, 0, 0, 1], dtype=bool), reasons=["ok", qp, qp, "ok", brake, qp, "ok"])
    b = SimpleNamespace(ok=np.array([0, 1], dtype=bool), reasons=[qp, "ok"])
    assert infeasible_stops([a, b]) == {"total": 3, "after_accepted_step": 1}


@pytest.mark.slow
def test_the_fault_matrix_runs_on_the_local_models_boundary(tmp_path):
    """`faults --eye-param ...` (the local model by default): the spiral through a loop with
    every robot and sensor error at once (the combined class) builds the local-global model
    of the eye with those parameters, the filter bounds the motion by it (kind "local":
    d_safe + 3 sigma), and the true retina stays past the violation line."""
    from eval.cli import main

    out = tmp_path / "faults"
    argv = ["faults", "--shape", "detached", "--eye-param", "height_mm=2.5", "--classes", "combined",
            "--scenarios", "3", "--duration-s", "0.2", "--jobs", "1", "--out", str(out)]
    assert main(argv) == 0
    result = json.loads((out / "faults.json").read_text())
    assert result["model"] == "local" and result["eye_params"] == {"height_mm": 2.5}
    c = result["classes"]["combined"]  # every robot and sensor error at once
    p = c["parameters"]
    assert (p["actuator_delay_ms"], p["actuator_lag_ms"], p["oct_time_offset_ms"]) == (5.0, 20.0, 2.6)
    assert p["floater_rate"] > 0 and p["encoder_noise_deg"] > 0 and p["sensor_pose_error"][2] < 0
    assert c["model"]["kind"] == "local"
    assert c["model"]["sigma3_coverage"] >= 0.99  # 3 sigma: 99.7 % of a normal error
    assert c["violations"] == 0 and c["contacts"] == 0
    assert c["min_true_clearance_mm"] >= result["violation_threshold_mm"]
