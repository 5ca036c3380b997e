"""Sphere geometry and fit_sphere.

Exact cases: the distance to a sphere is analytic (r - |q - c|), so the brute-force
reference (tests/conftest.py) is checked with its derived bounds and every other figure
to float64 round-off. fit_sphere solves a linear least-squares problem that noise-free
points satisfy exactly: recovery to 1e-6 mm (design.md), observed ~1e-12 mm.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from models import Sphere, fit_sphere

TOL_MM = 1e-6
ROUND_OFF_MM = 1e-9
PROPERTY = settings(max_examples=30)

spheres = st.builds(
    Sphere, st.lists(st.floats(-300.0, 300.0), min_size=3, max_size=3), st.floats(5.0, 15.0)
)


def cap(s: Sphere, seed: int, n: int = 300, max_polar_deg: float = 110.0) -> np.ndarray:
    """Random points on the cap of s within `max_polar_deg` of its -z pole (a scan's view)."""
    rng = np.random.default_rng(seed)
    cos_t = rng.uniform(np.cos(np.radians(max_polar_deg)), 1.0, n)
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    sin_t = np.sqrt(1.0 - cos_t**2)
    return s.center + s.radius * np.column_stack([sin_t * np.cos(phi), sin_t * np.sin(phi), -cos_t])


@PROPERTY
@given(spheres, st.integers(0, 2**32 - 1))
def test_noise_free_points_give_back_centre_and_radius(s, seed):
    f = fit_sphere(cap(s, seed))
    np.testing.assert_allclose(f.center, s.center, rtol=0, atol=TOL_MM)
    assert f.radius == pytest.approx(s.radius, abs=TOL_MM)


@PROPERTY
@given(spheres, st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1), st.lists(st.floats(-200, 200), min_size=3, max_size=3))
def test_fit_is_invariant_to_rotation_and_translation_of_noisy_data(s, seed, rot_seed, t):
    P = cap(s, seed) + np.random.default_rng(seed).normal(0.0, 0.02, (300, 3))
    R = Rotation.random(random_state=rot_seed).as_matrix()
    f, g = fit_sphere(P), fit_sphere(P @ R.T + t)
    np.testing.assert_allclose(g.center, R @ f.center + t, rtol=0, atol=TOL_MM)
    assert g.radius == pytest.approx(f.radius, abs=TOL_MM)


def test_four_points_define_the_sphere_and_fewer_are_refused():
    s = Sphere([1.0, -2.0, 3.0], 7.0)
    P = s.center + 7.0 * np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0]], dtype=float)
    f = fit_sphere(P)
    np.testing.assert_allclose(f.center, s.center, atol=1e-12)
    assert f.radius == pytest.approx(7.0, abs=1e-12)
    with pytest.raises(ValueError, match="at least 4 points"):
        fit_sphere(P[:3])


@pytest.mark.parametrize("kind", ["coplanar", "collinear"])
def test_flat_data_is_refused(kind):
    a = np.linspace(0, 2 * np.pi, 40, endpoint=False)
    P = np.column_stack([np.cos(a), np.sin(a), np.zeros(40)]) * 9.0 if kind == "coplanar" else np.outer(np.linspace(-5, 5, 40), [1, 2, 3])
    with pytest.raises(ValueError, match="coplanar or collinear"):
        fit_sphere(P @ Rotation.from_euler("xy", [0.3, 0.2]).as_matrix().T + 100.0)


# ---- geometry ------------------------------------------------------------------------------

S = Sphere([3.0, -4.0, 20.0], 11.0)


def queries(s: Sphere, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    U = rng.normal(size=(400, 3))
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    scales = np.concatenate([rng.uniform(0.0, 2.0, 300), rng.uniform(0.99, 1.01, 60), rng.uniform(10, 100, 40)])
    axes = np.concatenate([np.outer([0.5, 1.0, 1.5], e) for e in np.vstack([np.eye(3), -np.eye(3)])])
    return s.center + np.vstack([U * s.radius * scales[:, None], axes * s.radius])


def test_signed_distance_is_analytic_and_matches_brute_force(brute_force_distance):
    Q = queries(S)
    d = S.signed_distance(Q)
    np.testing.assert_allclose(d, S.radius - np.linalg.norm(Q - S.center, axis=1), rtol=0, atol=ROUND_OFF_MM)
    d_ref, h = brute_force_distance(S.center, np.full(3, S.radius), np.eye(3), Q, 300, 600)
    kappa = 1.0 / S.radius
    upper = np.sqrt(d * d + h * h * (1.0 + np.where(d < 0, kappa * np.abs(d), 0.0)))
    assert np.all(np.abs(d) <= d_ref + ROUND_OFF_MM) and np.all(d_ref <= upper + ROUND_OFF_MM)
    assert S.signed_distance(S.center)[0] == S.radius  # centre: exactly the radius, > 0 inside


def test_closest_point_and_gradient():
    Q = queries(S, seed=1)
    X = S.closest_point(Q)
    np.testing.assert_allclose(np.linalg.norm(X - S.center, axis=1), S.radius, atol=ROUND_OFF_MM)
    np.testing.assert_allclose(np.linalg.norm(Q - X, axis=1), np.abs(S.signed_distance(Q)), atol=ROUND_OFF_MM)
    G = S.gradient(Q)
    np.testing.assert_allclose(np.linalg.norm(G, axis=1), 1.0, atol=1e-12)
    step = 1e-5  # away from the centre (the only medial point): central differences to ~1e-10
    Q = Q[np.linalg.norm(Q - S.center, axis=1) > 1.0]
    fd = np.stack([(S.signed_distance(Q + step * u) - S.signed_distance(Q - step * u)) / (2 * step) for u in np.eye(3)], 1)
    np.testing.assert_allclose(S.gradient(Q), fd, rtol=0, atol=1e-7)
    # at the centre the gradient is undefined: a unit vector by convention, and the closest
    # point the pole it points away from (so that q = x + d * gradient still holds)
    g = S.gradient(S.center)[0]
    assert np.linalg.norm(g) == pytest.approx(1.0, abs=1e-15)
    np.testing.assert_allclose(S.closest_point(S.center), [S.center - S.radius * g], atol=ROUND_OFF_MM)


def test_sample_surface_is_on_the_sphere_and_cropped():
    P = S.sample_surface(30, 40, z_max=5.0)
    assert P.shape == (1200, 3)
    np.testing.assert_allclose(np.linalg.norm(P - S.center, axis=1), S.radius, atol=ROUND_OFF_MM)
    assert np.all(P[:, 2] - S.center[2] <= 5.0 + ROUND_OFF_MM)


def test_volume():
    assert S.volume == pytest.approx(4.0 / 3.0 * np.pi * 11.0**3, rel=1e-15)


@pytest.mark.parametrize("radius", [0.0, -1.0, np.nan, np.inf, "r"])
def test_bad_radius_is_refused(radius):
    with pytest.raises(ValueError, match="radius"):
        Sphere(np.zeros(3), radius)


@pytest.mark.parametrize("center", [[0.0, np.nan, 0.0], [0.0, 0.0], [np.inf, 0.0, 0.0]])
def test_bad_centre_is_refused(center):
    with pytest.raises(ValueError, match="center"):
        Sphere(center, 10.0)


@pytest.mark.parametrize("Q", [np.zeros((4, 2)), [[0.0, np.nan, 0.0]], [[np.inf, 0.0, 0.0]]])
def test_bad_points_are_refused(Q):
    for method in (S.signed_distance, S.gradient, S.closest_point):
        with pytest.raises(ValueError, match="Q"):
            method(Q)
    P = np.vstack([np.eye(3), -np.eye(3)])
    with pytest.raises(ValueError, match="P"):
        fit_sphere(np.vstack([P, Q]) if np.shape(Q)[1] == 3 else P[:, :2])


@PROPERTY
@given(spheres)
def test_of_fit_holds_what_the_checked_constructor_holds(s):
    # the sphere filter's unchecked constructor: the same sphere, its centre read-only
    fit = Sphere.of_fit(np.array(s.center, dtype=float), s.radius)
    np.testing.assert_array_equal(fit.center, s.center)
    assert fit.radius == s.radius and not fit.center.flags.writeable
    Q = cap(s, 0, n=20) * 0.9
    np.testing.assert_array_equal(fit.signed_distance(Q), s.signed_distance(Q))


@pytest.mark.parametrize("center, radius", [([np.nan, 0.0, 0.0], 11.0), ([0.0, np.inf, 0.0], 11.0), ([0.0, 0.0, 0.0], 0.0),
                                            ([0.0, 0.0, 0.0], -1.0), ([0.0, 0.0, 0.0], np.nan)])
def test_of_fit_refuses_what_the_checked_constructor_refuses(center, radius):
    with pytest.raises(ValueError, match="must be finite|radius"):
        Sphere.of_fit(np.array(center), radius)
