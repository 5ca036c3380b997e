"""Each A-scan's share of a sample in the local model (LocalConfig.sample_length_mm,
models.local.kernels.absorb_points): a scan line weighs its length on the retina, not its
A-scans; a still beam counts once; and, given the beams' directions, the distance noise
along the beam adds no length (an oblique beam's noise would otherwise read as lateral
steps: a slower scan, more A-scans per mm, would count more samples from the same line)."""
from __future__ import annotations

import numpy as np
import pytest

from models import AdaptiveEyeModel, Ellipsoid, PredictiveCriteria
from models.local.config import LocalConfig
from models.local.grid import LocalRetinaModel
from tests.models.local.test_local_model import NOISE_MM, cap_points, model_on_the_globe

O_W = np.array([0.0, -9.0, 2.0])  # mm: a beam origin inside the 11 mm globe: 43 deg incidence on the arc


def arc_points(spacing_mm, length_mm=6.0):
    """Points every `spacing_mm` along a 6 mm arc of an 11 mm globe, 20 deg off the posterior
    pole, whose radius ripples by 50 um over 4.4 mm: one scan line."""
    s = np.arange(0.0, length_mm, spacing_mm)
    a = (s - 0.5 * length_mm) / 11.0
    tilt = np.radians(20.0)
    u = np.c_[np.sin(a), -np.sin(tilt) * np.cos(a), -np.cos(tilt) * np.cos(a)]
    return u, (11.0 + 0.05 * np.sin(s / 0.7))[:, None] * u


def beamed(P, noise_mm, seed):
    """The points P (N, 3) mm seen along beams from O_W, each moved along its beam by
    Gaussian noise of noise_mm: (measured points, beam directions)."""
    B = P - O_W
    B /= np.linalg.norm(B, axis=1, keepdims=True)
    return P + np.random.default_rng(seed).normal(0.0, noise_mm, (len(P), 1)) * B, B


def model_of(P, B):
    """model_on_the_globe's model, given the beams B (N, 3) too."""
    m = LocalRetinaModel(np.zeros(3))
    g = Ellipsoid(np.zeros(3), np.array([11.0, 11.0, 11.0]))
    for k in range(0, len(P), 20):
        m.update(P[k:k + 20], g, beam_W=B[k:k + 20])
    m.solve_all()
    return m


def test_a_scan_line_weighs_its_length_not_its_a_scans():
    """A-scans closer than LocalConfig.sample_length_mm share one sample: the same line
    sampled every 5 um and every 10 um (both far denser than 0.2 mm) gives the same model,
    off the line too (the sums are two Riemann sums of one line integral: they differ by
    O(spacing / sample length)). Counted one by one, the denser line would weigh twice."""
    u, _ = arc_points(0.2)
    rng = np.random.default_rng(3)
    Q = u[rng.integers(0, len(u), 300)] + rng.normal(0.0, 0.06, (300, 3))  # up to ~10 deg off the line
    Q /= np.linalg.norm(Q, axis=1, keepdims=True)
    R5, S5 = model_on_the_globe(arc_points(0.005)[1]).radius_and_sd(Q)
    R10, S10 = model_on_the_globe(arc_points(0.01)[1]).radius_and_sd(Q)
    assert np.max(np.abs(R5 - R10)) < 5e-4  # mm: 1 % of the ripple
    np.testing.assert_allclose(S5, S10, rtol=0.01)


def test_noise_along_the_beams_adds_no_length():
    """The same 6 mm line measured with the paper's 20 um noise along beams 43 deg oblique
    to the retina, every 2.5 um and every 7.5 um (a scan at a third of the speed): given
    the beams, both count the line's length over sample_length_mm plus the first A-scan's
    whole sample, 1 + 6 / 0.2 = 31 samples (the ripple lengthens the line by < 0.5 %).
    Without them the noise's lateral part (20 um x sin 43 deg against 2.5 um steps) counts
    the dense line several times over (the control that this test can fail)."""
    expected = 1.0 + 6.0 / LocalConfig().sample_length_mm
    for spacing_mm, seed in ((0.0025, 1), (0.0075, 2)):
        P, B = beamed(arc_points(spacing_mm)[1], NOISE_MM, seed)
        incidence = np.degrees(np.arccos(np.abs(np.sum(B * P, axis=1) / np.linalg.norm(P, axis=1))))
        assert 40.0 < np.median(incidence) < 46.0  # deg
        assert model_of(P, B).n_samples == pytest.approx(expected, rel=0.01)
        assert model_on_the_globe(P).n_samples > 2.0 * expected


@pytest.mark.parametrize("oblique", [False, True])
def test_a_still_beam_counts_once(oblique):
    """A beam held still measures one spot again and again: those A-scans add nothing to
    the first (a still beam's errors are one error), whether its noise lies along the
    radius or, given the beam's direction, along an oblique beam."""
    u = np.array([[0.2, -0.1, -0.97]])
    u /= np.linalg.norm(u)
    rng = np.random.default_rng(0)
    first = 11.0 * u
    beam = (first - O_W) / np.linalg.norm(first - O_W) if oblique else u
    again = first + rng.normal(0.0, NOISE_MM, (500, 1)) * beam
    _, P = cap_points(lambda v: np.full(len(v), 11.0), n=3000, cap_deg=40.0)
    Q = P[::5] / 11.0
    B = P / np.linalg.norm(P, axis=1, keepdims=True)  # the cap's noise is radial
    held_P = np.vstack([P, first, again])
    held_B = np.vstack([B, beam, np.repeat(beam, 500, axis=0)])
    once = model_of(np.vstack([P, first]), np.vstack([B, beam])).radius_and_sd(Q)
    held = model_of(held_P, held_B).radius_and_sd(Q)
    # mm: the sums' rounding; along an oblique beam the held A-scans' directions from the
    # centre spread by the noise's lateral part (~1e-3 rad), which moves the nearest data
    # angle of the nodes about them: a nanometre, 1e-4 of the sd
    np.testing.assert_allclose(held[0], once[0], rtol=0.0, atol=1e-6 if oblique else 1e-9)
    np.testing.assert_allclose(held[1], once[1], rtol=1e-4 if oblique else 0.0, atol=0.0 if oblique else 1e-9)
    if not oblique:  # radial noise: the rule without beams counts it once too
        chord = model_on_the_globe(held_P).radius_and_sd(Q)
        np.testing.assert_allclose(chord[1], once[1], rtol=0.0, atol=1e-9)


def test_the_model_passes_each_kept_points_beam_on():
    """AdaptiveEyeModel.update's beams follow its points through the gate and the dwell
    rule (a beam held on one spot past its cap): every kept point's beam is its own (the
    gate's pending first point, an A-scan of the packet before, takes its neighbour's:
    within 1e-3 rad here); a floater's and non-finite rows' are dropped with them; a model
    without a local part keeps none."""
    u, P = arc_points(0.01)
    P_m, B = beamed(P, NOISE_MM, 4)
    P_m[57] += 3.0 * B[57]  # a floater 3 mm behind the retina
    P_m[90] = np.nan
    model = AdaptiveEyeModel(criteria=PredictiveCriteria(), local=LocalRetinaModel(np.zeros(3)))
    for k in range(0, len(P_m), 20):
        model.update(P_m[k:k + 20], B[k:k + 20])
        A, AB = model.last_accepted, model.last_beams
        assert AB is not None and AB.shape == A.shape
        own = (A - O_W) / np.linalg.norm(A - O_W, axis=1, keepdims=True)
        assert np.max(np.linalg.norm(own - AB, axis=1)) < 1e-3
    assert model.n_rejected_outliers >= 1
    held = P[-1] + np.random.default_rng(5).normal(0.0, NOISE_MM, (150, 1)) * B[-1]  # a beam held still: the dwell rule
    for k in range(0, 150, 20):
        model.update(held[k:k + 20], np.repeat(B[-1:], len(held[k:k + 20]), axis=0))
        if len(model.last_accepted):
            assert np.max(np.linalg.norm(model.last_beams - B[-1], axis=1)) < 1e-12
    assert model.n_dwelling > 0
    model.update(P_m[:3])
    assert model.last_beams is None
    quadric_only = AdaptiveEyeModel(criteria=PredictiveCriteria())
    quadric_only.update(P_m[:20], B[:20])
    assert len(quadric_only.last_accepted) and quadric_only.last_beams is None


def test_bad_beams_are_refused():
    model = AdaptiveEyeModel(criteria=PredictiveCriteria(), local=LocalRetinaModel(np.zeros(3)))
    _, P = arc_points(0.01)
    with pytest.raises(ValueError, match="beam_W must hold one beam direction per point: 20 rows, got 19"):
        model.update(P[:20], P[:19])
    with pytest.raises(ValueError, match="beam_W must be an"):
        model.update(P[:20], "up")
    B = np.full((20, 3), np.nan)  # no usable beam: those points take the rule without beams
    model.update(P[:20], B)
    assert model.n_received == 20


@pytest.mark.parametrize("bad", [np.inf, -np.inf])
def test_an_infinite_beam_counts_as_no_beam(bad):
    """A beam direction with an infinite component is no direction: the point's share is
    taken as without its beam (as a zero or NaN row is), n_samples stays finite."""
    P, B = beamed(arc_points(0.05)[1], NOISE_MM, 0)
    B_bad, B_none = B.copy(), B.copy()
    B_bad[7] = [bad, 0.0, 0.0]
    B_none[7] = 0.0
    a, b = model_of(P, B_bad), model_of(P, B_none)
    assert np.isfinite(a.n_samples) and a.n_samples == b.n_samples
    np.testing.assert_array_equal(a.params(True), b.params(True))
