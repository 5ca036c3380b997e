"""The command line as a new user meets it: flags refused in one line before anything is
written, every default and unit in --help, --version, Ctrl-C, and plan's messages naming
flags."""
from __future__ import annotations

import argparse
import math
import os
import signal
import subprocess
import sys
import time
from importlib.metadata import version
from pathlib import Path

import pytest
from test_mcap_log import decode_foxglove

from eval.cli import build_parser, main
from eval.cli.args import SEED_MAX, _Ranged
from eval.log.writer import read_log

ROOT = Path(__file__).resolve().parents[2]
NEEDS_OUT = {"paper", "eyes", "calibrate", "scan", "sensor", "plan"}  # --out is required


def run_main(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def subparsers() -> dict:
    parser = build_parser()
    (action,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(action.choices)


@pytest.mark.parametrize("command", ["demo", "boundary", "sensor", "plan", "faults"])
def test_a_negative_seed_is_one_line_naming_the_flag_and_its_range(command, tmp_path, capsys):
    out = tmp_path / "never"
    code, stdout, err = run_main(capsys, command, "--seed", "-1", "--out", out)
    assert code == 2 and stdout == ""
    assert err.count("\n") == 1, err  # one line
    assert err.startswith(f"vitreoguard {command}: error: argument --seed: ")
    assert f"[0, {SEED_MAX}]" in err and "got -1" in err
    assert not out.exists()


# (command, flag, a bad value, what the message names): every numeric flag of every subcommand
BAD_NUMBERS = [
    ("demo", "--scenarios", "0", "[1, 1000]"), ("demo", "--rows", "1", "[2, 1000]"), ("demo", "--seed", "x", "integer"),
    ("boundary", "--scenarios", "-3", "[1, 100000]"), ("boundary", "--sphere-scenarios", "-1", "[0, 100000]"),
    ("boundary", "--duration-s", "nan", "[0.05, 10] s"), ("boundary", "--spiral-speed-mm-s", "100", "[1, 17] mm/s"),
    ("boundary", "--spiral-revolutions", "inf", "[1, 18]"), ("boundary", "--seed", "1e3", "integer"),
    ("boundary", "--search-budget", "0", "[1, 1000000]"), ("boundary", "--actuator-delay-ms", "-1", "[0, 50] ms"),
    ("boundary", "--actuator-lag-ms", "nan", "[0, 200] ms"),
    ("boundary", "--actuator-accel-limit", "0", "[100, 100000] deg/s^2"),
    ("boundary", "--oct-time-offset-ms", "-2.6", "[0, 100] ms"), ("boundary", "--encoder-noise", "inf", "[0, 1] deg"),
    ("faults", "--scenarios", "0", "[1, 100000]"), ("faults", "--duration-s", "0", "[0.05, 10] s"),
    ("faults", "--seed", "-1", f"[0, {SEED_MAX}]"),
    ("sensor", "--outliers", "0.9", "[0, 0.5]"), ("sensor", "--speed-mm-s", "0", "[1, 17] mm/s"),
    ("sensor", "--revolutions", "18.5", "[1, 18]"), ("sensor", "--seed", str(SEED_MAX + 1), f"[0, {SEED_MAX}]"),
    ("plan", "--standoff-mm", "-1", "(0, 5] mm"), ("plan", "--sweep-mm", "nan", "[0.2, 5] mm"),
    ("plan", "--tip-speed-mm-s", "0", "[0.1, 20] mm/s"), ("plan", "--trust-angle-deg", "181", "(0, 180] deg"),
    ("plan", "--band", "5,0", "z0 < z1"), ("plan", "--band", "1", "'z0,z1' in mm"), ("plan", "--seed", "-2", "[0, "),
    ("plan", "--port-angle-deg", "91", "(0, 90] deg"), ("plan", "--port-limbus-mm", "2.9", "[3, 5] mm"),
    ("plan", "--survey-mm", "3.1", "[0, 3] mm"), ("plan", "--survey-passes", "5", "[1, 4]"),
    ("calibrate", "--poses", "9", "[10, 10000]"), ("calibrate", "--noise-um", "-1", "[0, 500] um"),
    ("calibrate", "--offset-um", "inf", "[0, 500] um"), ("calibrate", "--tilt-deg", "6", "[0, 5] deg"),
    ("calibrate", "--seed", "-1", f"[0, {SEED_MAX}]"),
    ("scan", "--tip-speed-mm-s", "60", "[0.1, 50] mm/s"), ("scan", "--revolutions", "0.1", "[0.5, 18]"),
    ("paper", "--seeds", "0", "[1, 100]"), ("paper", "--noise-um", "-1", "[0, 500] um"),
    ("paper", "--stride", "0", "[1, 50]"), ("paper", "--grid", "5", "[10, 2000]"), ("paper", "--jobs", "0", "[1, 1024]"),
    ("boundary", "--jobs", "-2", "[1, 1024]"), ("faults", "--jobs", "0", "[1, 1024]"),
    ("replay", "--tol", "-1", ">= 0 rad/s"),
    ("record", "--time-offset-ms", "150", "[-100, 100] ms"), ("record", "--revolutions", "0.1", "[0.5, 18]"),
    ("record", "--speed-mm-s", "0", "[1, 17] mm/s"), ("record", "--sync-s", "0.5", "[1, 10] s"),
    ("record", "--encoder-noise-urad", "-1", "[0, 1000] urad"), ("record", "--joint-rate-hz", "10", "[50, 1000] Hz"),
    ("record", "--seed", "-1", f"[0, {SEED_MAX}]"),
    ("fit", "--max-offset-ms", "0", "[1, 1000] ms"), ("fit", "--icp-max-distance-mm", "9", "[0.01, 5] mm"),
    ("fit", "--jobs", "0", "[1, 1024]"), ("demo", "--scenarios", "1_0", "[1, 1000]"),
    ("boundary", "--actuator-accel-limit", "1e300", "[100, 100000] deg/s^2"),
    ("boundary", "--actuator-delay-ms", "0.3", "[0, 50] ms, whole multiples of 1 ms"),
    ("plan", "--sweep-mm", "0", "[0.2, 5] mm"), ("plan", "--tip-speed-mm-s", "25", "[0.1, 20] mm/s"),
    ("eyes", "--wall-mm", "0", "[0.2, 5] mm"), ("eyes", "--edge-mm", "3", "[0.05, 2] mm"),
]


def test_the_table_covers_every_numeric_flag():
    flags = {(name, a.option_strings[-1]) for name, p in subparsers().items() for a in p._actions
             if isinstance(a.type, _Ranged) or a.dest == "band"}
    assert flags == {(c, f) for c, f, _, _ in BAD_NUMBERS}


@pytest.mark.parametrize("command, flag, value, names", BAD_NUMBERS)
def test_every_numeric_flag_is_checked_before_anything_is_written(command, flag, value, names, tmp_path, capsys):
    out = tmp_path / "never"
    argv = [command, flag, value, "--out", out] if command != "replay" else [command, tmp_path / "x.mcap", flag, value]
    code, stdout, err = run_main(capsys, *argv)
    assert code == 2 and stdout == ""
    assert err.count("\n") == 1 and f"argument {flag}: must be" in err and names in err, err
    assert not out.exists() and os.listdir(tmp_path) == []


# values argparse alone takes for unknown flags ("expected one argument"): each reaches its flag's own check
NEGATIVE_LOOKING = [("boundary", "--seed", "-inf", f"[0, {SEED_MAX}]"), ("boundary", "--scenarios", "-1e3", "[1, 100000]"),
                    ("boundary", "--duration-s", "-nan", "[0.05, 10] s"), ("plan", "--standoff-mm", "-1e-3", "(0, 5] mm"),
                    ("plan", "--seed", "-.5", f"[0, {SEED_MAX}]"), ("record", "--time-offset-ms", "-1e3", "[-100, 100] ms")]


@pytest.mark.parametrize("command, flag, value, names", NEGATIVE_LOOKING)
def test_a_value_that_reads_as_a_negative_number_is_the_flags_value(command, flag, value, names, tmp_path, capsys):
    out = tmp_path / "never"
    code, stdout, err = run_main(capsys, command, flag, value, "--out", out)
    assert code == 2 and stdout == ""
    assert err.count("\n") == 1 and f"argument {flag}: must be" in err and names in err and value in err, err
    assert not out.exists() and os.listdir(tmp_path) == []


def test_negative_numbers_in_any_form_are_values_not_flags():
    args = build_parser().parse_args(["plan", "--band", "-1,2", "--port-limbus-mm", "4", "--out", "x"])
    assert args.band == (-1.0, 2.0)
    args = build_parser().parse_args(["record", "--time-offset-ms", "-2.5e0", "--out", "x"])
    assert args.time_offset_ms == -2.5


def test_help_shows_every_default_and_every_numbers_unit_or_range():
    for name, parser in subparsers().items():
        text = parser.format_help()
        for action in parser._actions:
            if action.default in (None, argparse.SUPPRESS) or action.required or not action.option_strings:
                continue
            shown = str(action.default) if not isinstance(action.default, list) else str(action.default)
            assert f"(default: {shown})" in " ".join(text.split()), (name, action.dest)
            if isinstance(action.type, _Ranged):  # its unit, and its range (plan: the planner's, in words)
                help_text = " ".join(action.help.split())
                assert action.type.unit in help_text, (name, action.dest)
                assert action.type.range in help_text or (name == "plan" and "mm" in help_text), (name, action.dest)
    demo = " ".join(subparsers()["demo"].format_help().split())
    assert "(default: 20)" in demo and "[1, 1000]" in demo and "(default: emmetropic)" in demo


def test_version_comes_from_the_package_metadata(capsys):
    code, out, _ = run_main(capsys, "--version")
    assert code == 0 and out == f"vitreoguard {version('vitreoguard')}\n"


@pytest.mark.parametrize("standoff", ["0.55", "0.65", "0.76"])
def test_a_standoff_inside_the_filters_boundary_is_refused_before_the_scan(standoff, tmp_path, capsys):
    """The filter's boundary without the model's margin is d_safe 0.5 mm + the calibration
    margin (FilterConfig().boundary_mm(0)); the standoff needs 0.2 mm beyond it, named as
    the flag, before the model-building scan (no planner parameter named, nothing written)."""
    from safety import FilterConfig

    least = FilterConfig().boundary_mm(0.0) + 0.2
    code, stdout, err = run_main(capsys, "plan", "--out", tmp_path / "never", "--no-execute", "--standoff-mm", standoff)
    assert code == 2 and stdout == "" and err.count("\n") == 1
    assert err.startswith(f"vitreoguard plan: error: --standoff-mm {standoff} is below the filter's boundary"), err
    assert f"use at least {math.ceil(least * 100) / 100:.2f} mm" in err  # rounded up: the value given is taken
    for parameter in ("spacing_mm", "standoff_mm", "tip_speed_mm_s", "z_min", "z_max"):
        assert parameter not in err
    assert not (tmp_path / "never").exists()


def test_the_delay_flags_step_is_the_loops_control_period():
    from eval.cli.loop_flags import DELAY_MS
    from eval.loop_config import LoopConfig

    assert DELAY_MS.step == pytest.approx(1e3 / LoopConfig().control_rate_hz)


@pytest.mark.slow
def test_ctrl_c_stops_a_run_cleanly(tmp_path):
    """SIGINT during the logged spiral: exit 130, one 'interrupted' line and no traceback
    on stderr, nothing on stdout, and the open log closed (complete, its last event the
    interruption)."""
    out = tmp_path / "run"
    env = {**os.environ, "VITREOGUARD_NO_PROGRESS": "1"}
    child = subprocess.Popen([sys.executable, "-m", "eval.cli", "boundary", "--scenarios", "5", "--out", str(out)],
                             cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # as in a terminal
    try:
        deadline = time.monotonic() + 900.0  # on a fresh cache the child compiles the loop's kernels (1-3 min)
        log = out / "spiral.mcap"
        while not (log.exists() and log.stat().st_size > 200_000):  # the spiral is under way
            assert child.poll() is None and time.monotonic() < deadline, "the run did not get to its spiral"
            time.sleep(0.2)
        child.send_signal(signal.SIGINT)
        stdout, stderr = child.communicate(timeout=120)
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert child.returncode == 130, stderr
    assert stderr.strip() == "vitreoguard boundary: interrupted" and stdout == ""
    spiral = read_log(log)  # closed: not truncated
    assert not spiral.truncated and spiral.count("/filter/step") > 0
    _, event = spiral.messages["/log"][-1]  # the run's last event (model changes may come before it)
    assert decode_foxglove("/log", event).message == "run ended early: KeyboardInterrupt"
    assert not (out / "boundary.json").exists()


def test_an_interrupt_wrapped_by_compiled_code_is_still_an_interrupt():
    from eval.interrupts import is_interrupt

    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as inner:
            raise SystemError("returned a result with an exception set") from inner
    except SystemError as exc:
        assert is_interrupt(exc)
    assert not is_interrupt(SystemError("other")) and not is_interrupt(None)


@pytest.mark.parametrize("command", ["boundary", "sensor", "plan", "paper"])
@pytest.mark.parametrize("argv, words", [
    (["--eye-param", "height_mm"], ["argument --eye-param: must be NAME=VALUE"]),
    (["--eye-param", "height_mm=inf"], ["argument --eye-param: must be NAME=VALUE with a finite number"]),
    (["--shape", "detached", "--eye-param", "height_mm=9"], ["--eye-param: detached height_mm must be in (0, 5] mm"]),
    (["--shape", "detached", "--eye-param", "depth_mm=1"], ["no parameter 'depth_mm'", "height_mm (0, 5] mm"]),
    (["--shape", "detached", "--eye-param", "height_mm=1", "--eye-param", "height_mm=2"], ["height_mm given twice"]),
])
def test_a_wrong_eye_parameter_is_one_line_and_nothing_is_written(command, argv, words, tmp_path, capsys):
    out = tmp_path / "never"
    if command == "paper":
        argv = [("--shapes" if a == "--shape" else a) for a in argv]
    code, stdout, err = run_main(capsys, command, *argv, "--out", out)
    assert code == 2 and stdout == "" and err.count("\n") == 1, err
    assert all(w in err for w in words), err
    assert not out.exists()


def test_paper_takes_all_shapes_and_each_shape_once(tmp_path, capsys):
    """--shapes all is the six shapes (so a detachment's parameter out of range is refused by
    the detached eye's rule); a shape given twice is run once."""
    code, stdout, err = run_main(capsys, "paper", "--shapes", "all", "--eye-param", "height_mm=9", "--out", tmp_path / "a")
    assert code == 2 and stdout == "" and "detached height_mm must be in (0, 5] mm" in err, err
    code, _, err = run_main(capsys, "paper", "--shapes", "myopic", "myopic", "--eye-param", "height_mm=3",
                            "--out", tmp_path / "b")
    assert code == 2 and "eye shape 'myopic' has no parameter 'height_mm'" in err, err  # one shape, its own rule
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_paper_applies_an_eye_parameter_to_the_shapes_that_take_it_and_refuses_one_none_takes(tmp_path, capsys):
    code, _, err = run_main(capsys, "paper", "--shapes", "emmetropic", "myopic", "--eye-param", "height_mm=3",
                            "--out", tmp_path / "never")
    assert code == 2 and "none of the shapes emmetropic myopic takes it" in err
    import json

    out = tmp_path / "paper"
    code, _, _ = run_main(capsys, "paper", "--shapes", "detached", "--eye-param", "height_mm=3.5", "--stride", "50",
                          "--grid", "40", "--jobs", "1", "--out", out)
    assert code == 0
    low = json.loads((out / "table2.json").read_text())["detached"]
    code, _, _ = run_main(capsys, "paper", "--shapes", "detached", "--eye-param", "height_mm=0.5", "--stride", "50",
                          "--grid", "40", "--jobs", "1", "--out", tmp_path / "paper2")
    high = json.loads((tmp_path / "paper2" / "table2.json").read_text())["detached"]
    # a 3.5 mm detachment is a larger departure from any sphere than a 0.5 mm one: the sphere fit's
    # error over the reference region grows (the lift covers a 10 mm patch of a ~24 mm globe)
    assert low["sf_mae"][0] > high["sf_mae"][0]
