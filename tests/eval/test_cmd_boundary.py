"""`vitreoguard boundary` and `vitreoguard demo`: the JSON contract, plots and logs of a
reduced run, and bad arguments refused before anything is written."""
from __future__ import annotations

import json

import pytest

from eval.cli import main
from eval.log.replay import replay
from eval.loop_config import LoopConfig

KEYS = {"scenarios", "violations", "contacts", "min_true_clearance_mm", "intervention_fraction", "tracking_rmse_mm_s",
        "failsafe_stops", "stops_by_reason", "infeasible_qp_stops", "recovery_held_steps", "correction_eased_steps", "solve_us",
        "drake_diffik_us", "filter_replay_us", "realtime_factor"}


REDUCED = ["--scenarios", "3", "--sphere-scenarios", "2", "--duration-s", "0.3", "--spiral-revolutions", "2"]
# figures that depend on the simulation alone, not on wall time: the same whatever runs the scenarios
SIMULATED = ("violations", "contacts", "min_true_clearance_mm", "intervention_fraction", "tracking_rmse_mm_s",
             "failsafe_stops", "lens_violations", "max_rcm_error_um", "free_tracking_error_p99")


@pytest.fixture(scope="module")
def boundary_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("boundary")
    code = main(["boundary", *REDUCED, "--jobs", "2", "--out", str(out)])
    return code, out


def test_boundary_writes_the_contract(boundary_run):
    code, out = boundary_run
    assert code == 0
    r = json.loads((out / "boundary.json").read_text())
    assert KEYS <= set(r)
    assert r["scenarios"] == 3 and r["violations"] == 0 and r["contacts"] == 0
    assert r["min_true_clearance_mm"] >= 0.45
    assert isinstance(r["recovery_held_steps"], int) and r["recovery_held_steps"] >= 0
    assert isinstance(r["correction_eased_steps"], int) and r["correction_eased_steps"] >= 0
    assert set(r["solve_us"]) == {"median", "p99"} and set(r["drake_diffik_us"]) == {"median", "p99"}
    assert set(r["filter_replay_us"]) == {"median", "p99"} and r["filter_replay_us"]["p99"] > 0
    assert r["realtime_factor"] > 0 and 0.0 <= r["intervention_fraction"] <= 1.0
    # the first scenario goes to the MCAP log step by step, the others not: reported apart
    assert r["realtime_factor_unlogged"] > 0
    assert r["sphere_phase"]["scenarios"] == 2 and r["sphere_phase"]["violations"] == 0
    assert r["sphere_phase"]["model"]["kind"] == "prior"  # half a turn of spiral: no model trusted yet
    # the spiral's samples: the iiOCT's rate over the scan (one packet either way)
    config = LoopConfig()
    assert r["model"]["samples"] == pytest.approx(config.sensor_rate_hz * r["spiral"]["duration_s"], abs=config.sensor_packet)
    assert 0 <= r["model"]["oblique_samples"] <= r["model"]["samples"]
    for name in ("boundary_clearance.png", "boundary_activity.png", "spiral.mcap", "boundary.mcap"):
        assert (out / name).stat().st_size > 1000


@pytest.mark.slow
def test_one_worker_gives_the_figures_of_two(boundary_run, tmp_path):
    _, out = boundary_run
    assert main(["boundary", *REDUCED, "--jobs", "1", "--out", str(tmp_path)]) == 0
    one, two = (json.loads((d / "boundary.json").read_text()) for d in (tmp_path, out))
    for part in (lambda r: r, lambda r: r["sphere_phase"]):
        for key in SIMULATED:
            assert part(one)[key] == pytest.approx(part(two)[key], abs=1e-12, rel=0), key
    assert one["model"] == two["model"]


def test_the_sphere_phase_reports_the_model_its_scenarios_start_from(tmp_path):
    """A 4-turn spiral's first turn builds a sphere: boundary.json's sphere_phase.model reports it as
    `model` reports the built one. On this healthy eye no reference sample lies beyond 3 sigma on the
    side the barrier relies on (a young model's misses lie inside the retina), and the short build
    was probed on the way (every 0.25 s of its scan)."""
    assert main(["boundary", "--scenarios", "1", "--sphere-scenarios", "1", "--duration-s", "0.2",
                 "--spiral-revolutions", "4", "--jobs", "1", "--out", str(tmp_path)]) == 0
    r = json.loads((tmp_path / "boundary.json").read_text())
    young, built = r["sphere_phase"]["model"], r["model"]
    assert young["kind"] in ("local", "ellipsoid", "sphere") and set(built) - {"transition_at", "ef_mae_um", "sf_mae_um",
                                                                             "n_points", "outliers_rejected"} <= set(young)
    assert young["fitted_kind"] == "sphere" and built["fitted_kind"] == "ellipsoid"
    assert young["mae_um"] > built["mae_um"]  # a quarter of the scan: the built model is the better one
    assert young["sigma3_unsafe_fraction"] == 0.0 and 0.0 < young["sigma3_coverage"] <= 1.0
    assert young["on_the_way"]["probes"] >= 1


def test_the_first_scenario_log_replays(boundary_run):
    _, out = boundary_run
    result = replay(out / "boundary.mcap")
    assert result.ok and result.steps >= 285  # 0.3 s at 1 kHz from the first sensor packet (11 ms) on


@pytest.mark.slow
def test_the_quadric_boundary_runs_and_replays(tmp_path):
    """`--model quadric`: the loop's filter keeps the quadric's margins (no sigma in the model's
    figures), its campaign holds and its log replays step for step."""
    assert main(["boundary", *REDUCED, "--sphere-scenarios", "0", "--model", "quadric", "--jobs", "1",
                 "--out", str(tmp_path)]) == 0
    r = json.loads((tmp_path / "boundary.json").read_text())
    assert r["loop"]["model"] == "quadric" and r["model"]["sigma3_coverage"] is None
    assert r["violations"] == 0 and r["contacts"] == 0 and r["min_true_clearance_mm"] >= 0.45
    result = replay(tmp_path / "boundary.mcap")
    assert result.ok and result.steps >= 285


@pytest.mark.parametrize("argv, message", [
    (["--shape", "square"], "unknown shape"),
    (["--scenarios", "0"], "--scenarios"),
    (["--duration-s", "nan"], "--duration-s"),
    (["--spiral-speed-mm-s", "100"], "--spiral-speed-mm-s"),
    (["--actuator-lag-ms", "-1"], "--actuator-lag-ms"),
    (["--actuator-delay-ms", "inf"], "--actuator-delay-ms"),
    (["--actuator-accel-limit", "0"], "--actuator-accel-limit"),
    (["--oct-time-offset-ms", "nan"], "--oct-time-offset-ms"),
    (["--encoder-noise", "-0.01"], "--encoder-noise"),
    (["--calibration-bound", "-0.1,0.1"], "--calibration-bound"),
    (["--calibration-bound", "0.1"], "MM,DEG"),
    (["--sensor-pose-error", "1,2,3"], "DX,DY,DZ,RX,RY,RZ"),
    (["--shape", "all", "--eye-param", "height_mm=3"], "--eye-param needs one --shape"),
])
def test_bad_boundary_arguments_exit_2_and_write_nothing(argv, message, tmp_path, capsys):
    out = tmp_path / "never"
    assert main(["boundary", *argv, "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.parametrize("argv, message", [(["--shape", "round"], "unknown shape"), (["--scenarios", "0"], "--scenarios")])
def test_bad_demo_arguments_exit_2(argv, message, tmp_path, capsys):
    assert main(["demo", *argv, "--out", str(tmp_path / "never")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "never").exists()


@pytest.mark.parametrize("argv, message", [
    (["--classes", "lag,earthquake"], "--classes"), (["--calibration-bound", "nan,0.1"], "--calibration-bound"),
    (["--shape", "all", "--eye-param", "height_mm=3"], "--eye-param needs one --shape"),
    (["--shape", "detached", "--eye-param", "height_mm=9"], "height_mm must be in (0, 5] mm"),
    (["--shape", "pointed", "--eye-param", "depth_mm=2"], "has no parameter 'depth_mm'"),
])
def test_bad_faults_arguments_exit_2_and_write_nothing(argv, message, tmp_path, capsys):
    out = tmp_path / "never"
    assert main(["faults", *argv, "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.slow
def test_all_shapes_in_one_command_give_each_shapes_own_figures(tmp_path):
    """--shape all: every shape into OUT/<shape> and summary.json; a shape's figures are
    those of `--shape S` run alone (with another number of workers)."""
    reduced = ["--scenarios", "2", "--sphere-scenarios", "1", "--duration-s", "0.2", "--spiral-revolutions", "1.5"]
    assert main(["boundary", "--shape", "all", *reduced, "--jobs", "2", "--out", str(tmp_path / "all")]) == 0
    summary = json.loads((tmp_path / "all" / "summary.json").read_text())
    assert set(summary["shapes"]) == {"emmetropic", "myopic", "hyperopic", "detached", "staphyloma", "pointed"}
    assert all(r["scenarios"] == 2 for r in summary["shapes"].values()) and summary["wall_s"] > 0
    assert main(["boundary", "--shape", "staphyloma", *reduced, "--jobs", "1", "--out", str(tmp_path / "one")]) == 0
    lane, alone = (json.loads((tmp_path / d / "boundary.json").read_text()) for d in ("all/staphyloma", "one"))
    for key in SIMULATED:
        assert lane[key] == pytest.approx(alone[key], abs=1e-12, rel=0), key
    assert lane["model"] == alone["model"]


def test_shape_all_replaces_the_shape_and_out_flags_it_re_runs():
    """Every form argparse accepts for --shape and --out (spaced, =, an unambiguous
    abbreviation) is dropped; the other flags and their values stay."""
    from eval.cli.boundary_all import without

    argv = ["boundary", "--shape", "all", "--scenarios", "5", "--out=x", "--sh=all", "--ou", "y", "--seed", "3"]
    assert without(argv, ("--shape", "--out")) == ["boundary", "--scenarios", "5", "--seed", "3"]
