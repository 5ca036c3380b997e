"""The closed-loop commands' flags give the loop the filter it documents: with no flags, the
boundary `boundary` and `faults` evaluate is LoopConfig's own (d_safe + k sigma with the
loop's k), and a flag changes only what it names."""
from __future__ import annotations

import dataclasses

import pytest

from eval.cli import build_parser
from eval.cli.loop_flags import loop_config
from eval.loop_config import LoopConfig


@pytest.mark.parametrize("command", ["boundary", "faults"])
def test_no_flags_give_the_loops_own_filter(command):
    args = build_parser().parse_args([command, "--shape", "pointed"])
    assert loop_config(args).filter == LoopConfig().filter


@pytest.mark.parametrize("command", ["boundary", "faults"])
def test_the_model_flag_gives_each_model_its_own_filter(command):
    """By default the local-global model bounds the motion at d_safe + 3 sigma; `--model
    quadric` the quadric with its phase margins (k = 1 on its coverage misfit)."""
    default = loop_config(build_parser().parse_args([command]))
    local = loop_config(build_parser().parse_args([command, "--model", "local"]))
    quadric = loop_config(build_parser().parse_args([command, "--model", "quadric"]))
    assert default == local and local.local_model and local.filter.sigma_factor == 3.0
    assert not quadric.local_model and quadric.filter == LoopConfig(local_model=False).filter
    assert quadric.filter.sigma_factor == 1.0 and LoopConfig().local_model


@pytest.mark.parametrize("argv", [["sensor", "--out", "x"], ["plan", "--out", "x"]])
def test_sensor_and_plan_take_the_model_flag(argv):
    """sensor's spiral is bounded like boundary's (local by default); plan's default is the
    quadric (the band is never measured: README, Plan a peripheral vitrectomy)."""
    from eval.cli.loop_flags import local_model

    parser = build_parser()
    assert local_model(parser.parse_args(argv)) == (argv[0] == "sensor")
    assert local_model(parser.parse_args([*argv, "--model", "local"]))
    assert not local_model(parser.parse_args([*argv, "--model", "quadric"]))


def test_an_unknown_model_is_a_one_line_usage_error(capsys):
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args(["boundary", "--model", "mesh"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "--model" in err and "choose from local, quadric" in err


def test_a_calibration_bound_changes_only_the_bound():
    args = build_parser().parse_args(["boundary", "--calibration-bound", "0.05,0.2"])
    expected = dataclasses.replace(LoopConfig().filter, calibration_bound_mm=0.05, calibration_bound_deg=0.2)
    assert loop_config(args).filter == expected


def test_the_results_record_the_true_sensor_pose_error_given_or_not():
    """boundary.json's `loop` says which true sensor pose error the run simulated: the
    scenario's default (0.02 mm along x, 0.1 deg about y) when the flag is not given."""
    import numpy as np

    from eval.cli.loop_flags import loop_record, scenario

    for argv, error in ((["boundary"], [0.02, 0.0, 0.0, 0.0, 0.1, 0.0]),
                        (["boundary", "--sensor-pose-error", "0.1,0,0,0,0,0.5"], [0.1, 0.0, 0.0, 0.0, 0.0, 0.5])):
        args = build_parser().parse_args(argv)
        recorded = loop_record(args, loop_config(args))["sensor_pose_error"]
        assert recorded == pytest.approx(error, abs=1e-12)
        sc = scenario(args)  # the pose the loop simulates is the recorded one
        assert np.allclose(np.append(sc.sensor_offset_S_mm, np.degrees(sc.sensor_rotvec_S_rad)), recorded, atol=1e-12)
