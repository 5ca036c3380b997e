"""`vitreoguard sensor`: the full chain's figures on a reduced spiral, the JSON contract,
floaters rejected, bad arguments refused."""
from __future__ import annotations

import json

import numpy as np
import pytest

from eval.cli import main

KEYS = {"distance_bias_um", "distance_sd_um", "invalid_fraction", "outliers_rejected", "ef_mae_um", "sf_mae_um",
        "kind_final"}


def run(tmp_path, *argv):
    out = tmp_path / "sensor"
    assert main(["sensor", "--out", str(out), "--revolutions", "5", "--speed-mm-s", "17", *argv]) == 0
    return json.loads((out / "sensor.json").read_text()), out


@pytest.fixture(scope="module")
def clean_run(tmp_path_factory):
    return run(tmp_path_factory.mktemp("clean"))


def test_the_full_chain_meets_the_extraction_and_model_targets(clean_run):
    """A-scans -> distances -> points (calibration error of the paper's calibration) ->
    model: extraction |bias| <= 5 um and SD <= 20 um, and EF MAE <= 50 um even on this
    shorter spiral (5 turns; the command's default is 6). Fewer turns are not enough: the
    calibration error's imprint on the points depends on the instrument's orientations
    along the path, which 3 or 4 turns sample too sparsely for a steady EF MAE (3 turns:
    39-57 um for paths of the same extent; 4 turns: 48, 5: 38, 6: 37 um)."""
    r, out = clean_run
    assert KEYS <= set(r)
    assert abs(r["distance_bias_um"]) <= 5.0 and r["distance_sd_um"] <= 20.0
    assert r["kind_final"] == "ellipsoid" and r["ef_mae_um"] <= 50.0
    assert 0.0 <= r["invalid_fraction"] < 0.2
    assert (out / "ascans.png").stat().st_size > 10_000
    # the spiral is bounded by the local-global model (the default, --model local): its sigma's figures are
    # reported, and 3 sigma covers the true retina (the issue's >= 0.99) with no miss on the unsafe side
    m = r["model"]
    assert m["sigma3_coverage"] >= 0.99 and m["sigma3_unsafe_fraction"] == 0.0 and m["on_the_way"]["probes"] > 0


def test_floaters_on_5_percent_of_the_beams_change_the_ef_mae_by_at_most_10_percent(clean_run, tmp_path):
    """Floaters (35-55 dB sheets in the vitreous, the retina is 45 dB) on 5 % of the
    A-scans; same seed otherwise."""
    clean, _ = clean_run
    dirty, _ = run(tmp_path, "--outliers", "0.05")
    assert dirty["kind_final"] == "ellipsoid"
    assert abs(dirty["ef_mae_um"] - clean["ef_mae_um"]) <= 0.10 * clean["ef_mae_um"]


def test_the_quadric_model_flag_reaches_the_loop(tmp_path):
    """`--model quadric`: the spiral is bounded by the quadric, which has no sigma to report."""
    out = tmp_path / "quadric"
    argv = ["sensor", "--out", str(out), "--revolutions", "2", "--speed-mm-s", "17", "--mode", "distance"]
    assert main([*argv, "--model", "quadric"]) == 0
    m = json.loads((out / "sensor.json").read_text())["model"]
    assert m["sigma3_coverage"] is None and m["on_the_way"] is None and m["kind"] in ("sphere", "ellipsoid")


@pytest.mark.parametrize("argv, message", [(["--shape", "cube"], "unknown shape"), (["--outliers", "0.9"], "--outliers"),
                                           (["--revolutions", "0"], "--revolutions")])
def test_bad_arguments_exit_2(argv, message, tmp_path, capsys):
    assert main(["sensor", "--out", str(tmp_path / "never"), *argv]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "never").exists()


# Clean "distance"-mode runs of this spiral (5 turns, 17 mm/s) over seeds 0-5 end at EF MAE
# 41.3, 40.0, 40.6, 40.6, 40.6, 40.5 um: seed-to-seed SD 0.40 um, at most 0.84 um at 95 %
# confidence (chi-square, 5 degrees of freedom). A dirty run draws its noise from another
# stream than the clean one (the floater draws come in between), so the two differ like
# two seeds: SD sqrt(2) x 0.84 um; 4 of those is the tolerance.
SEED_TO_SEED_TOLERANCE_UM = 4.0 * np.sqrt(2.0) * 0.84


@pytest.fixture(scope="module")
def clean_distance_run(tmp_path_factory):
    return run(tmp_path_factory.mktemp("clean_distance"), "--mode", "distance")[0]


@pytest.mark.parametrize("seed", [0, 3])
def test_confident_wrong_distances_on_5_percent_of_the_samples_leave_the_loop_model_intact(
        clean_distance_run, seed, tmp_path):
    """The worst case: in "distance" mode a floater is a CONFIDENT wrong distance (0.5 mm
    to the retina's), which only the model's gate can turn away. Only the gated points
    may mark the measured directions: a turned-away floater counted as retina would put
    a misfit of 8.6 mm into the tip's margin and stop the spiral (EF MAE 1.4 mm). Seeds
    3 and 0 put a floater on the very first A-scan, which the gate must check too (kept
    unchecked: EF MAE 226 / 56 um)."""
    dirty, _ = run(tmp_path, "--mode", "distance", "--outliers", "0.05", "--seed", str(seed))
    assert clean_distance_run["kind_final"] == dirty["kind_final"] == "ellipsoid"
    assert dirty["outliers_rejected"] > 0
    assert abs(dirty["ef_mae_um"] - clean_distance_run["ef_mae_um"]) <= SEED_TO_SEED_TOLERANCE_UM
