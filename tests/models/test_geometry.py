"""Sphere and Ellipsoid geometry: exact signed distance against brute force, on the
axes, at the centre and far outside; gradients; closest points; validation."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from models import Ellipsoid, Sphere

RADII = np.array([11.455, 11.365, 10.148])


def _rotation(seed):
    return Rotation.random(random_state=seed).as_matrix()


def _brute(shape, Q, n=1500):
    """Distance to the nearest of n x n surface samples, and that grid's worst spacing bound."""
    S = shape.sample_surface(n, n)
    return cKDTree(S).query(Q)[0]


@pytest.mark.parametrize("seed", [0, 1])
def test_ellipsoid_distance_matches_dense_sampling(seed):
    e = Ellipsoid([1.0, -2.0, 3.0], RADII, _rotation(seed))
    rng = np.random.default_rng(seed)
    Q = e.center + rng.normal(0, 7, (300, 3))
    exact = np.abs(e.signed_distance(Q))
    brute = _brute(e, Q)
    # brute force can only overestimate, by at most half the grid diagonal (<= 0.1 mm on a
    # 1500 x 1500 equal-area grid of an eye-sized ellipsoid, coarsest at the poles)
    assert np.all(brute >= exact - 1e-9)
    assert np.all(brute - exact <= 0.1)
    assert np.median(brute - exact) < 0.01


def test_ellipsoid_axes_centre_and_far_points_are_exact():
    e = Ellipsoid(np.zeros(3), RADII)
    a, b, c = RADII
    cases = {
        (0.0, 0.0, 0.0): c,  # the centre: nearest are the ends of the shortest axis
        (1.0, 0.0, 0.0): None,  # on the long axis, between the foci: leaves the axis
        (0.0, 0.0, 5.0): c - 5.0,  # on the shortest axis: straight to the pole
        (0.0, 0.0, -20.0): -(20.0 - c),
        (30.0, 0.0, 0.0): -(30.0 - a),
        (0.0, -25.0, 0.0): -(25.0 - b),
    }
    for q, expected in cases.items():
        d = e.signed_distance(np.array(q))[0]
        x = e.closest_point(np.array(q))[0]
        assert np.sum((x / RADII) ** 2) == pytest.approx(1.0, abs=1e-12)
        assert abs(d) == pytest.approx(np.linalg.norm(x - q), abs=1e-12)
        if expected is not None:
            assert d == pytest.approx(expected, abs=1e-12)
    # a point on the x axis between the foci: the closest point is off-axis and nearer than the x pole
    d_axis = e.signed_distance(np.array([1.0, 0, 0]))[0]
    assert d_axis < a - 1.0


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-30, 30), min_size=3, max_size=3), st.integers(0, 10_000))
def test_closest_point_is_on_surface_and_locally_optimal(q, seed):
    e = Ellipsoid([0.5, -0.2, 0.1], RADII, _rotation(seed))
    q = np.asarray(q)
    x = e.closest_point(q)[0]
    L = (x - e.center) @ e.rotation / e.radii
    assert L @ L == pytest.approx(1.0, abs=1e-9)
    d = np.linalg.norm(q - x)
    # no nearby surface point is closer (first-order optimality)
    U = (x - e.center) @ e.rotation / e.radii
    rng = np.random.default_rng(seed)
    V = U + 1e-3 * rng.normal(size=(50, 3))
    V /= np.linalg.norm(V, axis=1, keepdims=True)
    neighbours = e.center + (V * e.radii) @ e.rotation.T
    assert np.linalg.norm(neighbours - q, axis=1).min() >= d - 1e-9


def test_gradient_is_unit_and_matches_finite_differences():
    e = Ellipsoid([0, 0, 0], RADII, _rotation(3))
    rng = np.random.default_rng(3)
    Q = rng.normal(0, 4, (50, 3)) + [0, 0, -6]  # away from the medial surface
    G = e.gradient(Q)
    np.testing.assert_allclose(np.linalg.norm(G, axis=1), 1.0, atol=1e-12)
    h = 1e-5
    fd = np.column_stack([(e.signed_distance(Q + h * ax) - e.signed_distance(Q - h * ax)) / (2 * h) for ax in np.eye(3)])
    np.testing.assert_allclose(G, fd, atol=1e-5)


def test_sphere_distance_gradient_and_volume():
    s = Sphere([1.0, 2.0, 3.0], 12.0)
    Q = np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 10.0], [1.0, 2.0, 20.0]])
    np.testing.assert_allclose(s.signed_distance(Q), [12.0, 5.0, -5.0])
    np.testing.assert_allclose(s.gradient(Q[1:]), [[0, 0, -1.0], [0, 0, -1.0]])
    assert s.volume == pytest.approx(4 / 3 * np.pi * 12.0**3)
    assert Ellipsoid([0, 0, 0], [1.0, 2.0, 3.0]).volume == pytest.approx(4 / 3 * np.pi * 6.0)


def test_sampling_is_on_the_surface_and_cropped():
    e = Ellipsoid([0, 0, 0], RADII)
    S = e.sample_surface(50, 40, z_max=RADII[2] - 5.0)
    assert S.shape == (2000, 3)
    assert np.abs(e.signed_distance(S)).max() < 1e-9
    assert S[:, 2].max() <= RADII[2] - 5.0 + 1e-9


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: Sphere([0, 0, np.nan], 1.0), "center"),
        (lambda: Sphere([0, 0, 0], -1.0), "radius"),
        (lambda: Ellipsoid([0, 0, 0], [1.0, 0.0, 1.0]), "radii"),
        (lambda: Ellipsoid([0, 0, 0], [1.0, 1.0, 1.0], np.diag([1.0, 1.0, -1.0])), "reflection"),
        (lambda: Ellipsoid([0, 0, 0], [1.0, 1.0, 1.0], 2 * np.eye(3)), "orthonormal"),
        (lambda: Ellipsoid([0, 0], [1.0, 1.0, 1.0]), "center"),
        (lambda: Sphere([0, 0, 0], 1.0).signed_distance(np.zeros((4, 2))), "Q"),
        (lambda: Sphere([0, 0, 0], 1.0).signed_distance([[0, np.inf, 0]]), "Q"),
    ],
)
def test_bad_input_names_the_argument(make, match):
    with pytest.raises(ValueError, match=match):
        make()
