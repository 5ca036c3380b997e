"""`vitreoguard replay`: a logged toy run replays bit for bit; a tampered output is caught
(exit 1); an unreadable, corrupt or truncated log is refused with a clear message (exit 2)
and nothing is written."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import Writer
from test_mcap_log import DT, toy_inputs, write_toy_run

from eval.cli import main
from eval.log.writer import RunLogger, read_log
from eval.log.replay import replay
from models import Ellipsoid
from safety import FilterConfig, PointKinematics, SafetyFilter

STEPS = 300


@pytest.fixture(scope="module")
def toy_log(tmp_path_factory):
    return write_toy_run(tmp_path_factory.mktemp("replay") / "run.mcap", STEPS)


def run_cli(capsys, *argv):
    code = main(["replay", *map(str, argv)])
    out, err = capsys.readouterr()
    return code, out, err


def test_a_logged_run_replays_bit_for_bit(toy_log, tmp_path, capsys):
    code, out, _ = run_cli(capsys, toy_log, "--out", tmp_path)
    assert code == 0 and f"{STEPS} steps" in out and "all match" in out
    report = json.loads((tmp_path / "replay.json").read_text())
    assert report == {"steps": STEPS, "mismatches": 0, "max_abs_diff": 0.0, "ok": True, "truncated": False, "examples": []}


def test_the_report_goes_next_to_the_log_by_default(tmp_path, capsys):
    log = write_toy_run(tmp_path / "short.mcap", 20)
    assert run_cli(capsys, log)[0] == 0
    assert json.loads((tmp_path / "replay.json").read_text())["steps"] == 20


def test_the_logged_configuration_is_the_one_replayed(tmp_path):
    """A run with a non-default filter (tighter tip speed, larger margin, Clarabel) replays
    exactly only because the configuration travels with the log."""
    cfg = FilterConfig(d_safe_mm=0.8, max_tip_speed_mm_s=5.0, solver="clarabel")
    result = replay(write_toy_run(tmp_path / "cfg.mcap", 100, cfg))
    assert result.ok and result.max_abs_diff == 0.0


def test_every_input_field_survives_the_log(tmp_path):
    """An ellipsoid model, the lens keep-out with a shaft point, RCM rows, a roll row and
    a fault step (NaN command: zero output, a reason) all replay exactly."""
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    eye = Ellipsoid([0.2, -0.1, 0.0], [11.5, 12.3, 10.1], R)
    lens = Ellipsoid([0.0, 0.0, 7.8], [4.5, 4.5, 2.0])
    filt, p = SafetyFilter(), np.array([1.0, 0.0, -8.0])
    with RunLogger(tmp_path / "all.mcap", filt.config) as log:
        for k in range(50):
            v = [np.nan, 0.0, 0.0] if k == 25 else [2.0, 1.0, -3.0]
            x = toy_inputs(p, v, k * DT, model=eye, lens=lens, margin_mm=0.05,
                           lens_points=[PointKinematics("shaft", p + [0.0, 0.0, 3.0], np.eye(3))],
                           rcm_A=np.array([[0.0, 1.0, 0.0]]), rcm_b=np.array([0.0]),
                           J_roll=np.zeros((1, 3)), roll_rate_cmd=0.0)
            out = filt(x)
            log.log_filter_step(x, out)
            p = p + DT * out.qdot
    fault = read_log(tmp_path / "all.mcap").messages["/filter/status"][25][1]
    assert not fault["ok"] and "non-finite v_cmd_W" in fault["reason"]
    result = replay(tmp_path / "all.mcap")
    assert result.ok and result.steps == 50 and result.max_abs_diff == 0.0


def tampered_log(path, edit_step: int, **changes):
    """The toy run with the logged output of one step replaced: what a changed filter
    (or a damaged log) would show."""
    filt, p = SafetyFilter(), np.array([0.0, 0.0, -10.0])
    with RunLogger(path, filt.config) as log:
        for k in range(40):
            x = toy_inputs(p, [1.0, 2.0, -8.0], k * DT)
            out = filt(x)
            logged = out._replace(**{key: f(out) for key, f in changes.items()}) if k == edit_step else out
            log.log_filter_step(x, logged)
            p = p + DT * out.qdot
    return path


def test_a_tampered_output_is_detected(tmp_path, capsys):
    log = tampered_log(tmp_path / "t.mcap", 17, qdot=lambda o: o.qdot + [0.0, 1e-6, 0.0])
    code, out, _ = run_cli(capsys, log)
    assert code == 1 and "1 MISMATCH" in out and "step 17" in out
    report = json.loads((tmp_path / "replay.json").read_text())
    assert report["mismatches"] == 1 and not report["ok"]
    assert report["max_abs_diff"] == pytest.approx(1e-6, rel=1e-6)
    assert report["examples"][0]["step"] == 17
    assert report["examples"][0]["t"] == 17 * DT  # the mismatching step's time, not the last step's
    assert f"step 17 (t = {17 * DT} s)" in out
    assert run_cli(capsys, log, "--tol", "2e-6")[0] == 0  # within a looser tolerance


def test_each_mismatch_reports_its_own_time(tmp_path):
    """Two tampered steps: each example carries its step's logged time."""
    filt, p = SafetyFilter(), np.array([0.0, 0.0, -10.0])
    with RunLogger(tmp_path / "two.mcap", filt.config) as log:
        for k in range(30):
            x = toy_inputs(p, [1.0, 2.0, -8.0], k * DT)
            out = filt(x)
            log.log_filter_step(x, out._replace(qdot=out.qdot + 1e-3) if k in (4, 11) else out)
            p = p + DT * out.qdot
    result = replay(tmp_path / "two.mcap")
    assert [(e["step"], e["t"]) for e in result.examples] == [(4, 4 * DT), (11, 11 * DT)]


# a log in the format of commit 9d08e3a (`vitreoguard demo --scenarios 1`'s boundary.mcap:
# the first adversarial scenario, 0.5 s): log times are the simulation time alone, "/tf" and
# "/scene" are JSON, the writer is mcap's. Its filter-step records must stay readable.
MAIN_LOG = Path(__file__).resolve().parents[1] / "data" / "boundary_main_9d08e3a.mcap"


def test_a_log_in_the_9d08e3a_format_still_replays(tmp_path, capsys):
    log = read_log(MAIN_LOG)
    assert log.start_ns == 0 and log.count("/filter/inputs") == 489
    assert isinstance(log.messages["/scene"][0][1], dict)  # JSON there, decoded as such
    code, out, _ = run_cli(capsys, MAIN_LOG, "--out", tmp_path)
    assert code == 0 and "489 steps" in out and "all match" in out
    assert json.loads((tmp_path / "replay.json").read_text())["max_abs_diff"] <= 1e-9


def test_a_changed_verdict_is_detected_even_with_equal_rates(tmp_path, capsys):
    log = tampered_log(tmp_path / "v.mcap", 5, cutter_allowed=lambda o: not o.cutter_allowed)
    code, out, _ = run_cli(capsys, log)
    assert code == 1 and "cutter_allowed" in out


def _assert_refused(capsys, tmp_path, path, *words, extra=()):
    code, out, err = run_cli(capsys, path, "--out", tmp_path / "out", *extra)
    assert code == 2, out
    assert err.startswith("vitreoguard replay: error:") and all(w in err for w in words), err
    assert not (tmp_path / "out").exists() and not (tmp_path / "replay.json").exists()


def test_random_bytes_are_refused(tmp_path, capsys):
    bad = tmp_path / "random.mcap"
    bad.write_bytes(np.random.default_rng(0).bytes(4096))
    _assert_refused(capsys, tmp_path, bad, "not an MCAP file")


def test_a_truncated_log_is_refused_unless_asked(tmp_path, capsys):
    data = write_toy_run(tmp_path / "run.mcap", STEPS, flush_every_s=0.05).read_bytes()  # a chunk per 50 steps
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    _assert_refused(capsys, tmp_path, cut, "truncated", "--allow-truncated")
    code, out, _ = run_cli(capsys, cut, "--allow-truncated", "--out", tmp_path / "partial")
    report = json.loads((tmp_path / "partial" / "replay.json").read_text())
    assert code == 0 and report["truncated"] and 0 < report["steps"] < STEPS and report["max_abs_diff"] == 0.0


@pytest.mark.parametrize("where", [0.3, 0.5, 0.7])
def test_a_damaged_byte_is_refused(toy_log, tmp_path, capsys, where):
    """One flipped bit in the data section: a chunk or data-section CRC fails (or the
    damaged record cannot be parsed)."""
    data = bytearray(toy_log.read_bytes())
    data[int(where * len(data) * 0.8)] ^= 0x10  # the summary section is the last ~10 %
    bad = tmp_path / "flipped.mcap"
    bad.write_bytes(bytes(data))
    _assert_refused(capsys, tmp_path, bad, "cannot replay")


def test_missing_empty_and_foreign_files_are_refused(tmp_path, capsys):
    _assert_refused(capsys, tmp_path, tmp_path / "nope.mcap", "no such file")
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    _assert_refused(capsys, tmp_path, empty, "not an MCAP file", "empty")
    foreign = tmp_path / "foreign.mcap"  # a valid MCAP file that is no run log
    with open(foreign, "wb") as f:
        w = Writer(f)
        w.start()
        ch = w.register_channel("/other", "json", w.register_schema("x", "jsonschema", b"{}"))
        w.add_message(ch, 0, b"{}", 0)
        w.finish()
    _assert_refused(capsys, tmp_path, foreign, "/filter/config")


def test_bad_tolerance_is_refused(toy_log, tmp_path, capsys):
    for tol in ("-1", "nan", "inf"):
        _assert_refused(capsys, tmp_path, toy_log, "--tol", extra=("--tol", tol))


def test_unreadable_file_is_refused(toy_log, tmp_path, capsys):
    if os.geteuid() == 0:
        pytest.skip("root reads any file")
    locked = tmp_path / "locked.mcap"
    locked.write_bytes(toy_log.read_bytes())
    locked.chmod(0)
    _assert_refused(capsys, tmp_path, locked, "cannot open")
