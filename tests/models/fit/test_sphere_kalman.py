"""SphereKalmanFilter: the information-form filter equals the batch fit_sphere at every step.

Both solve the same linear least-squares problem (|p|^2 = 2 p.c + k), so any batching
must give the batch answer up to float64 round-off: 1e-6 mm (the design's tolerance),
observed ~1e-11 mm on 20 um noisy eye-sized patches up to 300 mm from the origin.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models import Sphere, SphereKalmanFilter, fit_sphere

TOL_MM = 1e-6


def noisy_cap(center, radius, seed, n=200):
    rng = np.random.default_rng(seed)
    U = rng.normal(size=(n, 3))
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    U[:, 2] = -np.abs(U[:, 2])  # the posterior half, as a scan sees it
    return np.asarray(center) + radius * U + rng.normal(0.0, 0.02, (n, 3))


@settings(max_examples=40)
@given(
    st.lists(st.floats(-300.0, 300.0), min_size=3, max_size=3),
    st.floats(5.0, 15.0),
    st.integers(0, 2**32 - 1),
    st.data(),
)
def test_filter_equals_batch_fit_for_any_batching(center, radius, seed, data):
    P = noisy_cap(center, radius, seed)
    cuts = sorted(data.draw(st.lists(st.integers(1, len(P) - 1), max_size=15, unique=True)))
    kf = SphereKalmanFilter()
    for chunk in np.split(P, cuts):
        kf.update(chunk)
    s, ref = kf.sphere, fit_sphere(P)
    assert kf.n_points == len(P)
    np.testing.assert_allclose(s.center, ref.center, rtol=0, atol=TOL_MM)
    assert s.radius == pytest.approx(ref.radius, abs=TOL_MM)


def test_filter_one_point_at_a_time_tracks_the_batch_fit_at_every_step():
    P = noisy_cap([2.0, -1.0, 280.0], 11.5, seed=3, n=120)
    kf = SphereKalmanFilter()
    for k, p in enumerate(P):
        kf.update(p)  # a single (3,) point is one A-scan
        if k >= 10:
            ref = fit_sphere(P[: k + 1])
            np.testing.assert_allclose(kf.sphere.center, ref.center, rtol=0, atol=TOL_MM)
            assert kf.sphere.radius == pytest.approx(ref.radius, abs=TOL_MM)


def test_noise_free_points_give_back_the_sphere():
    truth = Sphere([10.0, 20.0, -30.0], 12.0)
    kf = SphereKalmanFilter()
    kf.update(truth.sample_surface(10, 12, z_max=0.0))
    np.testing.assert_allclose(kf.sphere.center, truth.center, atol=TOL_MM)
    assert kf.sphere.radius == pytest.approx(truth.radius, abs=TOL_MM)
    c, r = kf.center_radius
    np.testing.assert_allclose(c, truth.center, atol=TOL_MM)


def test_no_estimate_before_four_points():
    kf = SphereKalmanFilter()
    assert kf.sphere is None and kf.center_radius is None
    P = Sphere(np.zeros(3), 10.0).sample_surface(3, 3)
    kf.update(P[:3])
    assert kf.sphere is None
    kf.update(np.empty((0, 3)))
    assert kf.n_points == 3
    kf.update(P[3:])
    assert kf.sphere.radius == pytest.approx(10.0, abs=TOL_MM)


@pytest.mark.parametrize("P", [np.zeros((3, 2)), [[0.0, np.nan, 1.0]], [[np.inf, 0.0, 1.0]], np.zeros((2, 3, 3))])
def test_bad_points_are_refused_and_leave_the_filter_unchanged(P):
    kf = SphereKalmanFilter()
    good = Sphere(np.zeros(3), 10.0).sample_surface(4, 4)
    kf.update(good)
    before = kf.sphere
    with pytest.raises(ValueError, match="P"):
        kf.update(P)
    assert kf.n_points == len(good)
    np.testing.assert_array_equal(kf.sphere.center, before.center)


def test_the_sphere_is_made_once_per_change_of_the_state():
    """`sphere` is the same object until the filter takes points (none: the same one), then
    a new one equal bit for bit to the Sphere of the new centre and radius."""
    kf = SphereKalmanFilter()
    P = noisy_cap([1.0, -2.0, 40.0], 11.0, seed=5)
    kf.update(P[:20])
    s = kf.sphere
    assert kf.sphere is s
    kf.update(np.empty((0, 3)))
    assert kf.sphere is s
    kf.update(P[20:])
    t = kf.sphere
    assert t is not s and kf.sphere is t
    c, r = kf.center_radius
    np.testing.assert_array_equal(t.center, c)
    assert t.radius == r != s.radius
