"""The paper's metrics on analytic cases (models.metrics)."""
from __future__ import annotations

import numpy as np
import pytest

from models import Ellipsoid, Sphere
from models.eyes import make_eye
from models.metrics import (MeanSD, SigmaHonesty, fmae_exact, mae_exact, mmae_exact, model_samples, nearest_sample_distance,
                            paper_metrics, sigma_honesty)

ROUND_OFF_MM = 1e-9


def test_mean_sd_is_of_absolute_values():
    m = MeanSD.of([-1.0, 1.0, -3.0, 3.0])
    assert (m.mean, m.sd) == (2.0, 1.0)
    assert m.as_list() == [2.0, 1.0]


@pytest.mark.parametrize("bad", [[], [1.0, np.nan], [np.inf]])
def test_mean_sd_refuses_empty_or_non_finite(bad):
    with pytest.raises(ValueError, match="distances"):
        MeanSD.of(bad)


def test_sphere_model_against_a_sphere_truth_0_1_mm_larger():
    model, truth = Sphere([1.0, 2.0, 3.0], 11.0), Sphere([1.0, 2.0, 3.0], 11.1)
    mae = mae_exact(model, truth.sample_surface(50, 80))
    assert mae.mean == pytest.approx(0.1, abs=ROUND_OFF_MM) and mae.sd == pytest.approx(0.0, abs=ROUND_OFF_MM)


def test_measured_points_offset_along_the_normal_give_that_offset():
    truth = make_eye("emmetropic")
    X = truth.reference_samples(30, 40)
    n = truth.gradient(X)  # inward unit normal
    offsets = np.random.default_rng(0).normal(0.0, 0.02, len(X))
    P = X + offsets[:, None] * n
    # the points stay within the focal distance, so each offset is exactly the distance
    assert mmae_exact(P, truth).mean == pytest.approx(np.abs(offsets).mean(), abs=ROUND_OFF_MM)
    assert fmae_exact(P, truth.ellipsoid).mean == pytest.approx(np.abs(offsets).mean(), abs=ROUND_OFF_MM)


def test_sampled_form_is_never_below_the_exact_form_and_within_the_sampling_error():
    truth = make_eye("myopic")
    model = Ellipsoid(truth.ellipsoid.center + [0.05, 0.0, -0.03], truth.radii * 1.01, truth.ellipsoid.rotation)
    T = truth.reference_samples(120, 120)
    exact = np.abs(model.signed_distance(T))
    M = model_samples(model, truth, 300, 300)
    sampled = nearest_sample_distance(T, M)
    # spacing of the model sampling: the largest nearest-neighbour gap bounds how far a surface
    # point can be from a sample (a sample is no farther than the largest gap from any point)
    gap = nearest_sample_distance(M[::7], np.delete(M, np.arange(0, len(M), 7), axis=0)).max()
    assert np.all(sampled >= exact - ROUND_OFF_MM)
    inner = np.abs(truth.pose.to_E(T)[:, 2]) < truth.anterior_z_mm - 6.0  # away from the crop edge
    assert np.all(sampled[inner] <= np.sqrt(exact[inner] ** 2 + (2 * gap) ** 2) + ROUND_OFF_MM)


def test_paper_metrics_of_the_true_ellipsoid():
    truth = make_eye("hyperopic")
    P = truth.reference_samples(40, 40)
    pm = paper_metrics(truth.ellipsoid, truth, P, n_grid=100)
    assert pm.mae.mean == pytest.approx(0.0, abs=ROUND_OFF_MM)
    assert pm.mmae.mean == pytest.approx(0.0, abs=ROUND_OFF_MM)
    assert pm.fmae.mean == pytest.approx(0.0, abs=ROUND_OFF_MM)
    # the cloud-to-cloud form adds the sampling error alone (100 x 100 over a ~11 mm eye: < 0.5 mm)
    assert 0.0 < pm.mae_sampled.mean < 0.5


@pytest.mark.parametrize("bad", [np.zeros((3, 2)), [[np.nan, 0.0, 0.0]]])
def test_bad_points_are_refused_naming_them(bad):
    truth = make_eye("emmetropic")
    with pytest.raises(ValueError, match="points"):
        mmae_exact(bad, truth)
    with pytest.raises(ValueError, match="truth_samples"):
        mae_exact(truth.ellipsoid, bad)


class _ShiftedSphere:
    """A sphere model 1 mm larger than the true 12 mm retina (its retina beyond the true
    one: each true sample lies 1 mm inside it, signed distance +1 mm) with a sigma that
    grows with the sample's height z: 0.2 mm + 0.05 z^2 / mm."""

    def __init__(self):
        self.sphere = Sphere(np.zeros(3), 13.0)

    def signed_distance(self, Q):
        return self.sphere.signed_distance(Q)

    def uncertainty(self, Q):
        return 0.2 + 0.05 * np.asarray(Q)[:, 2] ** 2


def test_sigma_honesty_counts_the_unsafe_side_beyond_three_sigma():
    # on the true 12 mm sphere the error is 1 mm everywhere: covered where 3 (0.2 + 0.05 z^2) >= 1, i.e. |z| >= 2 mm
    z = np.linspace(-11.0, 11.0, 2201)
    x = np.sqrt(144.0 - z ** 2)
    P = np.column_stack([x, np.zeros_like(z), z])
    h = sigma_honesty(_ShiftedSphere(), P)
    short = np.abs(z) < np.sqrt((1.0 / 3.0 - 0.2) / 0.05)  # 3 sigma < 1 mm there
    assert h.coverage == pytest.approx(1.0 - short.mean(), abs=1e-12)
    assert h.unsafe_fraction == pytest.approx(short.mean(), abs=1e-12)
    assert h.worst_excess_mm == pytest.approx(1.0 - 0.6, abs=1e-9)  # at z = 0: 1 mm - 3 x 0.2 mm


def test_sigma_honesty_misses_on_the_safe_side_are_not_unsafe():
    # the model's retina inside the true one (signed distance < 0 at the true samples): misses, none unsafe
    h = SigmaHonesty.of(np.array([-1.0, -0.1, 0.05]), np.array([0.1, 0.1, 0.1]))
    assert (h.coverage, h.unsafe_fraction) == (pytest.approx(2 / 3), 0.0)
    assert h.worst_excess_mm == pytest.approx(-0.25)
    assert np.isnan(SigmaHonesty.of(np.array([0.0]), np.array([np.inf])).coverage)


def test_sigma_honesty_of_no_samples_is_refused():
    with pytest.raises(ValueError, match="at least one point"):
        sigma_honesty(_ShiftedSphere(), np.zeros((0, 3)))
