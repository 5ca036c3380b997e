"""`vitreoguard calibrate`: the calibration.json contract, the targets, and bad input."""
from __future__ import annotations

import json

import numpy as np
import pytest

from eval.cli import main as cli_main

CONTRACT_KEYS = {
    "position_error_um", "direction_error_deg", "plane_residual_um", "plane_residual_max_um",
    "n_poses", "noise_um", "true", "recovered", "solve_time_s",
}


@pytest.fixture(scope="module")
def default_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("calibrate")
    assert cli_main(["calibrate", "--out", str(out)]) == 0
    return out, json.loads((out / "calibration.json").read_text())


def test_writes_the_contract_and_meets_the_targets(default_run):
    out, c = default_run
    assert CONTRACT_KEYS <= set(c)
    assert c["n_poses"] == 250 and c["noise_um"] == 20.0
    for pose in (c["true"], c["recovered"]):
        assert len(pose["p_FS_mm"]) == 3 and np.linalg.norm(pose["u_F"]) == pytest.approx(1.0, abs=1e-9)
    p_err = 1e3 * np.linalg.norm(np.subtract(c["recovered"]["p_FS_mm"], c["true"]["p_FS_mm"]))
    assert c["position_error_um"] == pytest.approx(p_err, rel=1e-9)
    assert c["position_error_um"] <= 20.0
    assert c["direction_error_deg"] <= 0.1
    assert c["plane_residual_um"] < 30.03 and c["plane_residual_max_um"] >= c["plane_residual_um"]
    assert all(c["meets_targets"].values())
    # the true pose really is off the nominal one by the defaults (300 um, 2 deg)
    assert 1e3 * np.linalg.norm(np.subtract(c["true"]["p_FS_mm"], c["nominal"]["p_FS_mm"])) == pytest.approx(300.0)
    assert np.degrees(np.arccos(np.dot(c["true"]["u_F"], c["nominal"]["u_F"]))) == pytest.approx(2.0)
    s = c["sensitivity"]
    assert len(s["offset_diameter_error_um"]) == len(s["offsets_um"])
    assert np.shape(s["tilt_diameter_error_um"]) == (len(s["azimuths_deg"]), len(s["tilts_deg"]))
    assert (out / "fig3_sensitivity.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_same_seed_same_result(default_run, tmp_path):
    _, c = default_run
    assert cli_main(["calibrate", "--out", str(tmp_path), "--seed", "0"]) == 0
    again = json.loads((tmp_path / "calibration.json").read_text())
    assert again["recovered"] == c["recovered"]


@pytest.mark.parametrize(
    "args, message",
    [
        (["--poses", "9"], "--poses"),
        (["--poses", "20000"], "--poses"),
        (["--noise-um", "-1"], "--noise-um"),
        (["--noise-um", "nan"], "--noise-um"),
        (["--offset-um", "inf"], "--offset-um"),
        (["--offset-um", "600"], "--offset-um"),
        (["--tilt-deg", "-0.5"], "--tilt-deg"),
        (["--tilt-deg", "6"], "--tilt-deg"),
        (["--seed", "-1"], "--seed"),
    ],
)
def test_bad_options_exit_2_and_write_nothing(tmp_path, capsys, args, message):
    out = tmp_path / "out"
    assert cli_main(["calibrate", "--out", str(out), *args]) == 2
    err = capsys.readouterr().err
    assert message in err and "error" in err
    assert not out.exists()


def test_unwritable_out_exits_2(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert cli_main(["calibrate", "--out", str(blocker / "sub")]) == 2
    assert "not writable" in capsys.readouterr().err
    assert blocker.read_text() == "x"


def test_non_numbers_are_refused_by_the_parser(tmp_path, capsys):
    assert cli_main(["calibrate", "--out", str(tmp_path / "out"), "--poses", "many"]) == 2
    assert "argument --poses: must be an integer in [10, 10000], got 'many'" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
