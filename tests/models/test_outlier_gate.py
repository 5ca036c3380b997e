"""The innovation gate keeps floaters out and lets real retina in."""
from __future__ import annotations

import numpy as np
import pytest

from models import AdaptiveEyeModel
from models.eyes import make_eye
from models.metrics import mae_exact
from models.outlier_gate import OutlierGate
from models.paper_scan import paper_scan


def _floater_scan(shape="emmetropic", rate=0.05, seed=1):
    """The paper's spiral with `rate` of the A-scans replaced by a floater 1.2-12 mm in
    front of the retina (20-90 % of the true distance)."""
    scan = paper_scan(make_eye(shape), seed=seed)
    rng = np.random.default_rng(seed + 100)
    hit = rng.random(len(scan)) < rate
    P = scan.points.copy()
    short = scan.distance_mm[hit] * rng.uniform(0.2, 0.9, hit.sum())
    P[hit] = scan.p_WT[hit] + scan.beam_W[hit] * short[:, None]
    return scan.points, P, hit


@pytest.fixture(scope="module")
def emmetropic_runs():
    clean, dirty, hit = _floater_scan()
    models = {}
    for name, P, gate in (("clean", clean, OutlierGate()), ("dirty", dirty, OutlierGate()), ("ungated", dirty, None)):
        m = AdaptiveEyeModel(gate=gate)
        for p in P:
            m.update(p)
        models[name] = m
    return models, hit


def test_floaters_are_rejected_and_counted(emmetropic_runs):
    models, hit = emmetropic_runs
    assert models["clean"].n_rejected_outliers == 0  # 20 um noise never trips a 1 mm / 6-sigma gate
    assert models["dirty"].n_rejected_outliers == hit.sum()
    assert models["dirty"].n_points == len(hit) - hit.sum()


def test_ellipsoid_accuracy_survives_five_percent_floaters(emmetropic_runs):
    models, _ = emmetropic_runs
    truth = make_eye("emmetropic").reference_samples(80, 80)
    clean = mae_exact(models["clean"].ellipsoid, truth).mean
    dirty = mae_exact(models["dirty"].ellipsoid, truth).mean
    ungated = mae_exact(models["ungated"].ellipsoid, truth).mean
    assert abs(dirty - clean) <= 0.10 * clean + 1e-3  # issue 5: within 10 % (1 um floor: noise level)
    assert ungated > 10 * clean  # without the gate the floaters wreck the fit


def test_a_run_of_far_points_is_structure_and_gets_in():
    scan = paper_scan(make_eye("myopic"), seed=2)
    m = AdaptiveEyeModel(gate=OutlierGate(max_consecutive=10))
    for p in scan.points[:400]:
        m.update(p)
    # from A-scan 400 on the retina is 3 mm closer (a detachment) and stays so: the first
    # ten such points are held back as possible floaters, the eleventh on is retina
    lifted = scan.points[400:440] - 3.0 * scan.beam_W[400:440]
    for p in lifted:
        m.update(p)
    assert m.n_rejected_outliers == 10
    assert m.n_points == 430


def test_gate_parameters_are_checked():
    with pytest.raises(ValueError, match="max_jump_mm"):
        OutlierGate(max_jump_mm=0.0)
    with pytest.raises(ValueError, match="window"):
        OutlierGate(window=0)
