"""`vitreoguard plan`: the JSON contract on a reduced band (plan only), bad input."""
from __future__ import annotations

import json

import pytest

from eval.cli import main

KEYS = {"coverage", "band_reachable", "min_model_clearance_mm", "min_true_clearance_mm", "duration_s", "path_length_mm",
        "min_joint_margin_deg", "filter_intervention_fraction", "plan_time_s"}


def test_plan_writes_the_contract(tmp_path):
    out = tmp_path / "plan"
    assert main(["plan", "--out", str(out), "--band", "0,2", "--no-execute"]) == 0
    r = json.loads((out / "plan.json").read_text())
    assert KEYS <= set(r)
    assert r["coverage"] >= 0.9 and 0.0 < r["band_reachable"] <= 1.0
    assert r["min_model_clearance_mm"] >= 0.95  # 1 mm standoff, spline within 50 um of the targets
    assert r["min_joint_margin_deg"] >= 4.5 and r["plan_time_s"] < 10.0
    assert r["min_true_clearance_mm"] is None and r["filter_intervention_fraction"] is None  # not executed
    assert (out / "coverage.png").stat().st_size > 10_000


@pytest.mark.parametrize("argv, message", [(["--standoff-mm", "0.4"], "--standoff-mm must be in (0.6, 5] mm"), (["--band", "x"], "--band"),
                                           (["--band", "9,12"], "outside the model"), (["--shape", "egg"], "unknown shape")])
def test_bad_plans_exit_2_and_write_nothing(argv, message, tmp_path, capsys):
    out = tmp_path / "never"
    assert main(["plan", "--out", str(out), "--no-execute", *argv]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_an_ellipsoid_that_is_no_eye_gives_way_to_the_sphere_and_its_wider_boundary(tmp_path, capsys):
    """The pointed eye's ellipsoid (fitted to its posterior cap) has semi-axes of 150 and 29
    mm: the filter bounds the motion with the sphere fit instead, whose phase margin
    (1 mm) puts the boundary at 1.5 mm, so a 1 mm standoff is refused before any motion."""
    out = tmp_path / "never"
    assert main(["plan", "--shape", "pointed", "--out", str(out)]) == 2
    assert "below the boundary the filter keeps from this sphere model (1.50 mm" in capsys.readouterr().err
    assert not out.exists()
