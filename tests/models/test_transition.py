"""The predictive criteria's compiled checkpoint tests, on the checkpoints of a spiral,
against the NumPy formulas they replaced, bit for bit."""
from __future__ import annotations

import math

import numpy as np
import pytest

from models import AdaptiveEyeModel
from models.ellipsoid_fit import LENGTH_SCALE_MM, taubin_residual
from models.extrapolation import _DIRECTIONS, _drift_and_gap, drift_and_gap
from models.eyes import make_eye
from models.paper_scan import paper_scan
from models.transition import PredictiveCriteria, _prequential_errors

_CHECKPOINTS: dict = {}
_RECORD: list = []


class _Recording(PredictiveCriteria):
    """PredictiveCriteria that keeps the arguments of each convergence test in _RECORD."""

    def _convergence(self, snap, v_ef_old):
        _RECORD.append((snap, v_ef_old.copy(), snap.S.copy()))
        return super()._convergence(snap, v_ef_old)


def _checkpoints(name: str = "emmetropic") -> list:
    """(FitSnapshot, the old ellipsoid's quadric, S then) of every convergence test of the
    paper's spiral on eye `name` in the loop's packets of 20 (S copied: the model's own
    changes; cached)."""
    if name not in _CHECKPOINTS:
        _RECORD.clear()
        model = AdaptiveEyeModel(_Recording())
        P = paper_scan(make_eye(name), noise_um=20.0, seed=1).points
        for k in range(0, 3000, 20):
            model.update(P[k:k + 20])
        _CHECKPOINTS[name] = list(_RECORD)
    return _CHECKPOINTS[name]


def _arguments(snap, v_old, S):
    c_ef, r_ef, R_ef = snap.ef
    return c_ef, r_ef, R_ef, snap.p0, LENGTH_SCALE_MM, S, PredictiveCriteria.crop_mm, v_old, *snap.sf


def test_the_convergence_test_decides_with_numpys_direction_exactly():
    """drift_and_gap normalises the anterior direction by a compiled sum of squares where
    that decides every point's crop as NumPy's norm would, and by NumPy's norm otherwise:
    at every checkpoint of a spiral its drift, gap and point count equal, bit for bit,
    those with NumPy's norm always (`undecided` inf), which the length alone changes in
    many of them (the sum of squares rounds as NumPy's BLAS dot product does not)."""
    points, differ = 0, 0
    for snap, v_old, S in _checkpoints():
        args = _arguments(snap, v_old, S)
        assert drift_and_gap(*args) == drift_and_gap(*args, undecided=np.inf)
        anterior = (snap.ef[0] - snap.p0) / LENGTH_SCALE_MM - S[6:9, 9] / (2.0 * S[9, 9])
        differ += math.sqrt(anterior.dot(anterior)) != np.sqrt(anterior[0] ** 2 + anterior[1] ** 2 + anterior[2] ** 2)
        points += drift_and_gap(*args)[2]
    assert len(_checkpoints()) > 50 and points > 0 and differ > 0


def test_a_crop_decided_by_the_last_bits_takes_numpys_direction():
    """When a point's height lies on the crop's cut (the crop made so), the compiled length
    leaves the decision to NumPy's: the kernel says so (-1), and drift_and_gap's answer
    is the one with NumPy's norm."""
    snap, v_old, S = _checkpoints()[-1]
    c_ef, r_ef, R_ef = snap.ef
    c = (c_ef - snap.p0) / LENGTH_SCALE_MM
    anterior = c - S[6:9, 9] / (2.0 * S[9, 9])
    anterior /= math.sqrt(anterior.dot(anterior))
    h = (_DIRECTIONS * (r_ef / LENGTH_SCALE_MM)) @ R_ef.T @ anterior
    crop_mm = LENGTH_SCALE_MM * (h.max() - np.sort(h)[len(h) // 2])  # the median height on the cut
    args = (c_ef, r_ef, R_ef, snap.p0, LENGTH_SCALE_MM, S, crop_mm, v_old, *snap.sf)
    assert _drift_and_gap(_DIRECTIONS, *args, -1.0, 1e-12)[2] == -1
    assert drift_and_gap(*args) == drift_and_gap(*args, undecided=np.inf)
    assert drift_and_gap(*args)[2] > 0


@pytest.mark.parametrize("name", ["emmetropic", "pointed"])
def test_the_prediction_errors_are_the_taubin_residuals_of_the_new_points(name):
    """_prequential_errors (one compiled call) equals LENGTH_SCALE_MM x taubin_residual of
    each old quadric over S - S_old, as NumPy and the kernel computed them one by one."""
    for snap, _, S in _checkpoints(name)[::5]:
        S_old = S * 0.75  # a scatter matrix with fewer (weighted) points
        pair = _prequential_errors(S, S_old, snap.v_sf, snap.v_ef, LENGTH_SCALE_MM)
        assert pair == (LENGTH_SCALE_MM * taubin_residual(S - S_old, snap.v_sf),
                        LENGTH_SCALE_MM * taubin_residual(S - S_old, snap.v_ef))
