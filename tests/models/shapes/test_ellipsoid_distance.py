"""The compiled ellipsoid distance answers every point: on the axis planes, on the axes, at
the centre and with equal semi-axes it agrees with the closest-point construction in
NumPy (Ellipsoid.closest_point) to 1e-9 mm.

The axes are signed permutations of the frame's (exact in float64), so a query with a
zero axis coordinate lies exactly on that axis's plane: the zero survives c + R L - c.
"""
from __future__ import annotations

import itertools

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from models import Ellipsoid
from models.shapes.ellipsoid_distance import ellipsoid_distance_and_gradient

TOL_MM = 1e-9
SIGNED_PERMUTATIONS = [np.eye(3)[list(p)] * s for p in itertools.permutations(range(3))
                       for s in itertools.product((-1.0, 1.0), repeat=3)]
PROPER = [R for R in SIGNED_PERMUTATIONS if np.linalg.det(R) > 0]


@st.composite
def ellipsoids(draw) -> Ellipsoid:
    """Semi-axes 2-20 mm, all distinct, two equal (any pair) or all equal; axes a signed
    permutation; centre within 50 mm."""
    r = [draw(st.floats(2.0, 20.0)) for _ in range(3)]
    equal = draw(st.sampled_from([(), (0, 1), (0, 2), (1, 2), (0, 1, 2)]))
    for i in equal[1:]:
        r[i] = r[equal[0]]
    R = PROPER[draw(st.integers(0, len(PROPER) - 1))]
    c = [draw(st.floats(-50.0, 50.0)) for _ in range(3)]
    return Ellipsoid(c, r, R)


@st.composite
def special_points(draw, e: Ellipsoid, n: int = 12) -> np.ndarray:
    """n queries whose axis coordinates are each 0 or within 3 semi-axes: points on the
    planes, on the axes and at the centre, inside and out, in e's frame."""
    L = np.zeros((n, 3))
    for k in range(n):
        for i in range(3):
            if draw(st.booleans()):
                L[k, i] = draw(st.floats(-3.0, 3.0)) * e.radii[i]
    return e.center + L @ e.rotation.T


def reference(e: Ellipsoid, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(signed distance, closest point) from Ellipsoid.closest_point."""
    X = e.closest_point(Q)
    L = (Q - e.center) @ e.rotation / e.radii
    d = np.linalg.norm(Q - X, axis=1)
    return np.where(np.sum(L * L, axis=1) < 1.0, d, -d), X


@settings(max_examples=300)
@given(st.data())
def test_every_point_agrees_with_the_closest_point_construction(data):
    """Distance to 1e-9 mm; the gradient is a unit vector whose step back by the distance
    lands on a closest point (Q - d g, at the reference's distance from Q and on the
    surface), and where the reference's closest point is the same point (no tie between
    mirrored closest points), the gradient is the reference's inward normal there."""
    e = data.draw(ellipsoids())
    Q = data.draw(special_points(e))
    d, g = e.signed_distance_and_gradient(Q)
    d_ref, X_ref = reference(e, Q)
    np.testing.assert_allclose(d, d_ref, rtol=0, atol=TOL_MM)
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0, rtol=0, atol=1e-12)
    X = Q - d[:, None] * g
    np.testing.assert_allclose(np.linalg.norm(Q - X, axis=1), np.abs(d_ref), rtol=0, atol=TOL_MM)
    np.testing.assert_allclose(e.signed_distance(X), 0.0, rtol=0, atol=TOL_MM)
    same = np.linalg.norm(X - X_ref, axis=1) <= 1e-6
    n_ref = -(((X_ref - e.center) @ e.rotation / e.radii**2) @ e.rotation.T)
    n_ref /= np.linalg.norm(n_ref, axis=1, keepdims=True)
    np.testing.assert_allclose(g[same], n_ref[same], rtol=0, atol=TOL_MM)


def test_the_centre_is_answered_by_the_plus_end_of_the_smallest_axis():
    e = Ellipsoid([1.0, 2.0, 3.0], [9.0, 12.0, 7.0], PROPER[5])
    d, g = e.signed_distance_and_gradient(e.center)
    axis = e.rotation[:, 2]  # the smallest semi-axis, 7 mm
    assert d[0] == 7.0
    np.testing.assert_allclose(g[0], -axis, rtol=0, atol=1e-15)
    np.testing.assert_allclose(e.closest_point(e.center)[0], e.center + 7.0 * axis, rtol=0, atol=1e-12)


def test_between_the_foci_on_the_plane_the_closest_point_leaves_the_plane():
    """On the plane of the smallest axis, inside the focal ellipse, the distance is to a
    point off the plane (Eberly's t = -e_min^2 case): shorter than to the plane's ellipse."""
    e = Ellipsoid(np.zeros(3), [12.0, 9.0, 6.0])
    q = np.array([[1.0, 0.5, 0.0]])
    d, g = e.signed_distance_and_gradient(q)
    x = q[0] - d[0] * g[0]
    assert abs(x[2]) > 1.0 and d[0] < 9.0 - 0.5
    np.testing.assert_allclose(d, reference(e, q)[0], rtol=0, atol=TOL_MM)


def test_non_finite_points_give_nan_in_the_kernel():
    e = Ellipsoid(np.zeros(3), [12.0, 9.0, 6.0])
    Q = np.array([[np.nan, 0.0, 0.0], [np.inf, 1.0, 1.0], [1.0, 2.0, 3.0]])
    d, g = ellipsoid_distance_and_gradient(e.center, e.rotation, e.radii, Q)
    assert np.isnan(d[:2]).all() and np.isnan(g[:2]).all()
    assert np.isfinite(d[2]) and np.isfinite(g[2]).all()
