"""Regression: a reduced paper experiment (one seed, every tenth A-scan) against the noise model.

Tolerances follow from the simulation: distance noise N(0, 20 um) along the beam.
- MMAE (points vs truth) is the mean |noise| projected on the surface normal:
  at most 20 um * sqrt(2/pi) = 15.96 um (normal incidence), somewhat less for oblique
  beams; with ~509 points its standard error is ~0.5 um.
- A correct ellipsoid absorbs none of the noise, so EF FMAE = MMAE within ~1 um.
- The full run reaches EF MAE <= 10 um; with a tenth of the points the parameter
  noise grows by sqrt(10), so the reduced bound is 10 um * sqrt(10) = 32 um.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from eval.cli import main as cli_main
from eval.experiments.paper import MAX_LAG, best_ellipsoid_curve, decision, optimal_transition, run_shape
from models.eyes import EyePose
from models.fit.robust_fit import RobustFitConfig

NOISE_MEAN_ABS_UM = 20.0 * np.sqrt(2.0 / np.pi)


@pytest.fixture(scope="module")
def reduced_runs():
    return {s: run_shape(s, seed=3, stride=10, grid=120, n_curve=40) for s in ("emmetropic", "myopic", "hyperopic", "staphyloma")}


@pytest.mark.parametrize("shape", ["emmetropic", "myopic", "hyperopic"])
def test_regular_shapes_meet_the_noise_model(reduced_runs, shape):
    run = reduced_runs[shape]
    mmae_um = 1e3 * run.ef.mmae.mean
    assert 12.0 < mmae_um < NOISE_MEAN_ABS_UM + 1.5
    assert abs(1e3 * run.ef.fmae.mean - mmae_um) < 1.0
    assert 1e3 * run.ef.mae.mean <= 10.0 * np.sqrt(10.0)
    # a sphere cannot follow these eyes: their semi-axes differ by 0.3-1.6 mm
    assert run.sf.mae.mean > 0.05
    # the paper's sampled form only adds discretisation error to the exact one
    assert run.ef.mae_sampled.mean >= run.ef.mae.mean - 1e-3
    assert run.transitions["predictive"] is not None
    assert run.optimal_transition_at is not None


def test_staphyloma_stays_a_sphere_where_the_sphere_is_better(reduced_runs):
    run = reduced_runs["staphyloma"]
    assert run.sf.mae.mean < run.ef.mae.mean
    assert run.optimal_transition_at is None
    assert run.transitions["predictive"] is None


def test_optimal_transition_definition():
    f = np.array([0.1, 0.2, 0.3, 0.4, 0.5])
    sf = np.array([1.0, 1.0, 1.0, 1.0, 1.0])
    assert optimal_transition(f, sf, np.array([2.0, 0.5, 2.0, 0.5, 0.5])) == 0.4
    assert optimal_transition(f, sf, np.array([0.5, 0.5, 0.5, 0.5, 0.5])) == 0.1
    assert optimal_transition(f, sf, np.array([0.5, 0.5, 0.5, 0.5, 2.0])) is None


def test_best_ellipsoid_curve_takes_either_fit_where_the_other_has_none():
    ef = np.array([np.nan, 2.0, 0.5, 0.7])
    globe = np.array([np.nan, np.nan, 0.9, 0.4])
    best = best_ellipsoid_curve(ef, globe)
    assert np.isnan(best[0]) and best[1:].tolist() == [2.0, 0.5, 0.4]


def test_the_sigma_along_the_spiral_is_the_worst_over_the_runs_where_any_had_a_field():
    """Before the local model's first field a curve point is NaN in every run: left out
    (no warning, which the suite turns into an error), and the worst taken over the runs
    that had one."""
    from types import SimpleNamespace

    from eval.cli.paper import honesty_along_spiral

    def run(cov, unsafe, excess_mm):
        return SimpleNamespace(fractions=np.array([0.1, 0.5, 1.0]), lc_coverage_curve=np.array(cov),
                               lc_unsafe_curve=np.array(unsafe), lc_excess_curve=np.array(excess_mm))

    h = honesty_along_spiral([run([np.nan, 0.9, 1.0], [np.nan, 0.0, 0.0], [np.nan, -0.05, -0.04]),
                              run([np.nan, np.nan, 0.98], [np.nan, np.nan, 0.01], [np.nan, np.nan, 0.002])])
    assert h["lowest_sigma3_coverage"] == 0.9 and h["lowest_at"] == 0.5
    assert h["largest_unsafe_fraction"] == 0.01 and h["largest_unsafe_at"] == 1.0
    assert h["worst_excess_um"] == pytest.approx(2.0) and h["end_coverage"] == 0.98


def test_cli_writes_the_contract(tmp_path):
    out = tmp_path / "paper"
    rc = cli_main(["paper", "--out", str(out), "--shapes", "myopic", "--stride", "20", "--grid", "60", "--jobs", "1"])
    assert rc == 0
    table = json.loads((out / "table2.json").read_text())
    entry = table["myopic"]
    for key in ("mmae", "sf_fmae", "sf_mae", "ef_fmae", "ef_mae"):
        assert len(entry[key]) == 2 and len(entry[key + "_sampled"]) == 2
        assert all(v >= 0 for v in entry[key])
    assert set(entry["criteria_met_at"]) == {"scan_range", "residual", "temporal"}
    for key in ("transition_at", "optimal_transition_at"):
        assert entry[key] is None or 0.0 <= entry[key] <= 1.0
    assert entry["paper"]["ef_mae"] == [0.038, 0.016]
    g = entry["global_quadric"]
    for key in ("transition_at", "optimal_transition_at", "lag"):
        assert g[key] is None or -1.0 <= g[key] <= 1.0
    assert isinstance(g["decision_right"], bool) and isinstance(g["timely"], bool) and len(g["per_seed"]) == 1
    assert 0.0 <= g["globe_mae"] < 1.0  # mm: the robust globe of a regular eye, fitted to every 20th A-scan
    h = entry["local_honesty"]
    assert 0.0 <= h["lowest_sigma3_coverage"] <= h["end_coverage"] <= 1.0 and 0.0 <= h["lowest_at"] <= 1.0
    assert 0.0 <= h["end_unsafe_fraction"] <= h["largest_unsafe_fraction"] <= 1.0
    assert (h["largest_unsafe_at"] is None) == (h["largest_unsafe_fraction"] == 0.0) == (h["worst_excess_um"] <= 0.0)
    assert (out / "table2.md").read_text().startswith("# Table 2")
    assert "## The local model's sigma along the spiral" in (out / "table2.md").read_text()
    assert (out / "fig5_myopic.png").stat().st_size > 10_000


@pytest.mark.parametrize("shape", ["emmetropic", "myopic", "hyperopic"])
def test_the_local_models_sigma_is_followed_along_the_spiral(reduced_runs, shape):
    """Each point of the curves holds the local field's SigmaHonesty once there is a global
    model; at the end of a regular eye's spiral the field is its ellipsoid's, within the
    0.3 mm far sd (3 sigma 0.9 mm) of an ellipsoid a few um off: every sample covered,
    none beyond on the unsafe side."""
    run = reduced_runs[shape]
    n = len(run.fractions)
    curves = (run.lc_coverage_curve, run.lc_unsafe_curve, run.lc_excess_curve)
    assert all(len(c) == n for c in curves)
    has = np.isfinite(run.lc_mae_curve)
    assert has[-1] and np.array_equal(has, np.isfinite(run.lc_coverage_curve))
    cov, unsafe = run.lc_coverage_curve[has], run.lc_unsafe_curve[has]
    assert np.all((0.0 <= cov) & (cov <= 1.0)) and np.all((0.0 <= unsafe) & (unsafe <= 1.0 - cov + 1e-12))
    assert cov[-1] == 1.0 and unsafe[-1] == 0.0 and run.lc_excess_curve[-1] < 0.0


@pytest.mark.parametrize(
    "args, message",
    [
        (["--shapes", "round"], "unknown shape"),
        (["--noise-um", "-1"], "--noise-um"),
        (["--seeds", "0"], "--seeds"),
        (["--fit", "robust", "--noise-um", "0"], "--fit robust"),
    ],
)
def test_cli_bad_input_exits_2_and_writes_nothing(tmp_path, capsys, args, message):
    out = tmp_path / "paper"
    assert cli_main(["paper", "--out", str(out), *args]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists() or not any(out.iterdir())


def test_cli_unwritable_output_exits_2(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    assert cli_main(["paper", "--out", str(blocker / "sub"), "--shapes", "myopic"]) == 2
    assert "not writable" in capsys.readouterr().err


@pytest.mark.parametrize("pose", ["nominal", "tilted"])
@pytest.mark.parametrize("shape", ["emmetropic", "myopic", "hyperopic", "pointed", "detached", "staphyloma"])
def test_robust_fit_decides_every_shape_in_time(shape, pose):
    """`paper --fit robust --seeds 1` (seed 0, every A-scan): with the robust ellipsoid
    (models.fit.robust_fit) the ellipsoid ends up better than the sphere on all six shapes,
    pathologies included, and the predictive criteria switch to it no earlier than the
    optimal point and within 10 % of the spiral after it (the lag target), also with the eye
    tilted 11 deg and decentred. (The lag is the target itself; on other noise seeds the
    regular eyes' lags are those of the least-squares fit, which for some seeds switch
    up to 15 % early on the emmetropic and myopic eyes: README.)"""
    eye_pose = EyePose.anatomical() if pose == "tilted" else EyePose()
    run = run_shape(shape, seed=0, pose=eye_pose, grid=60, n_curve=100, criteria=("predictive",), robust=RobustFitConfig())
    d = decision(run.transitions["predictive"], run.optimal_transition_at)
    assert run.optimal_transition_at is not None
    assert d["decision_right"] and 0.0 <= d["lag"] <= MAX_LAG


@pytest.mark.parametrize("criterion", ["paper", "predictive"])
def test_the_local_part_rides_on_the_driving_criterions_model(monkeypatch, criterion):
    """run_shape puts the local model on its first criterion's model, whose kind decides
    the quadric under the local part: the CLI lists the driving criterion first."""
    import eval.cli.paper as paper_cli

    seen = {}
    monkeypatch.setattr(paper_cli, "run_shape", lambda *a, **k: seen.update(k))
    args = {"pose": "nominal", "fit": "least-squares", "noise_um": 20.0, "stride": 1, "grid": 60,
            "eye_params": {"myopic": {}}, "criterion": criterion}
    paper_cli._task(("myopic", 0, args))
    assert seen["criteria"][0] == criterion and set(seen["criteria"]) == {"paper", "predictive"}
