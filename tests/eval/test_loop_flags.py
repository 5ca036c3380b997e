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
def test_the_local_model_flag_gives_its_own_filter(command):
    local = loop_config(build_parser().parse_args([command, "--local-model"]))
    assert local.local_model and local.filter == LoopConfig(local_model=True).filter
    assert local.filter.sigma_factor == 3.0 and LoopConfig().filter.sigma_factor == 1.0


def test_a_calibration_bound_changes_only_the_bound():
    args = build_parser().parse_args(["boundary", "--calibration-bound", "0.05,0.2"])
    expected = dataclasses.replace(LoopConfig().filter, calibration_bound_mm=0.05, calibration_bound_deg=0.2)
    assert loop_config(args).filter == expected
