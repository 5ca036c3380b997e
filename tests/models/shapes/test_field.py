"""The distance-field interface (models.shapes.field) of the spheres, ellipsoids and
ground-truth eyes: the compiled kernel equals the methods bit for bit, non-finite points
give NaN and an infinite uncertainty, and the distance is a distance (invariant under
rigid motions, its gradient the direction in which it grows)."""
from __future__ import annotations

import copy

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from models import Ellipsoid, Sphere
from models.eyes import EYE_SHAPES, EyePose, make_eye
from models.shapes.field import DistanceField, FieldKernel

SHAPES = {
    "sphere": Sphere([1.0, -2.0, 3.0], 11.0),
    "ellipsoid": Ellipsoid([4.0, -7.0, 30.0], [6.0, 12.0, 9.0], Rotation.from_euler("zyx", [0.7, -0.4, 1.1]).as_matrix()),
    "spheroid": Ellipsoid(np.zeros(3), [12.0, 12.0, 7.0]),
}


def points_around(shape, n: int = 400, seed: int = 0) -> np.ndarray:
    """Points inside, outside and near the shape, the centre among them (mm)."""
    rng = np.random.default_rng(seed)
    size = shape.radius if isinstance(shape, Sphere) else shape.radii.max()
    Q = shape.center + rng.normal(0.0, size, (n, 3))
    Q[0] = shape.center
    return Q


@pytest.mark.parametrize("name", list(SHAPES))
def test_the_kernel_is_the_methods_bit_for_bit(name):
    shape = SHAPES[name]
    assert isinstance(shape, DistanceField)
    fk = shape.field_kernel()
    assert isinstance(fk, FieldKernel)
    assert fk.params.dtype == np.float64 and fk.params.ndim == 1
    assert fk.params.flags.c_contiguous and fk.params.flags.writeable
    assert shape.field_kernel().params is fk.params  # made once per shape
    Q = points_around(shape)
    h, g, u = fk.kernel(fk.params, Q)
    d_m, g_m = shape.signed_distance_and_gradient(Q)
    assert np.array_equal(h, d_m) and np.array_equal(g, g_m)
    assert np.array_equal(h, shape.signed_distance(Q)) and np.array_equal(g, shape.gradient(Q))
    assert np.array_equal(u, np.zeros(len(Q))) and np.array_equal(shape.uncertainty(Q), u)


@pytest.mark.parametrize("name", list(SHAPES))
def test_non_finite_points_give_nan_and_infinite_uncertainty(name):
    shape = SHAPES[name]
    fk = shape.field_kernel()
    Q = np.array([[np.nan, 0.0, 0.0], [0.0, np.inf, 0.0], [0.0, 0.0, -np.inf], [1.0, 2.0, 3.0]])
    h, g, u = fk.kernel(fk.params, Q)
    assert np.isnan(h[:3]).all() and np.isnan(g[:3]).all() and np.isinf(u[:3]).all() and (u[:3] > 0).all()
    assert np.isfinite(h[3]) and np.isfinite(g[3]).all() and u[3] == 0.0
    assert np.array_equal(shape.uncertainty(Q), u)


@pytest.mark.parametrize("name", list(SHAPES))
def test_a_deep_copy_is_the_shape_itself(name):
    shape = SHAPES[name]
    assert copy.deepcopy(shape) is shape
    assert copy.deepcopy({"model": shape})["model"] is shape
    assert not shape.center.flags.writeable


@pytest.mark.parametrize("name", EYE_SHAPES)
def test_the_eyes_answer_as_distance_fields(name):
    eye = make_eye(name, EyePose.anatomical())
    assert isinstance(eye, DistanceField)
    rng = np.random.default_rng(1)
    Q = eye.pose.to_W(rng.normal(0.0, 6.0, (30, 3)))
    d, g = eye.signed_distance_and_gradient(Q)
    assert np.array_equal(d, eye.signed_distance(Q)) and np.array_equal(g, eye.gradient(Q))
    assert np.array_equal(eye.uncertainty(Q), np.zeros(len(Q)))
    if name in ("emmetropic", "myopic", "hyperopic"):
        fk = eye.field_kernel()
        h, g_k, u = fk.kernel(fk.params, Q)
        np.testing.assert_allclose(h, d, rtol=0, atol=1e-12)  # the methods take the points to E first
        np.testing.assert_allclose(g_k, g, rtol=0, atol=1e-12)
        assert np.array_equal(u, np.zeros(len(Q)))
    else:
        with pytest.raises(TypeError, match="no compiled distance field"):
            eye.field_kernel()


@st.composite
def shapes(draw):
    """A sphere or an ellipsoid (semi-axes 4-15 mm) at a random pose within 30 mm."""
    c = np.array([draw(st.floats(-30.0, 30.0)) for _ in range(3)])
    if draw(st.booleans()):
        return Sphere(c, draw(st.floats(4.0, 15.0)))
    R = Rotation.random(random_state=draw(st.integers(0, 2**32 - 1))).as_matrix()
    return Ellipsoid(c, [draw(st.floats(4.0, 15.0)) for _ in range(3)], R)


def moved(shape, R: np.ndarray, t: np.ndarray):
    """The shape after the rigid motion x -> R x + t."""
    if isinstance(shape, Sphere):
        return Sphere(R @ shape.center + t, shape.radius)
    return Ellipsoid(R @ shape.center + t, shape.radii, R @ shape.rotation)


@settings(max_examples=60)
@given(shapes(), st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1))
def test_the_distance_is_invariant_under_rigid_motions(shape, rot_seed, seed):
    rng = np.random.default_rng(seed)
    Q = shape.center + rng.normal(0.0, 10.0, (50, 3))
    R = Rotation.random(random_state=rot_seed).as_matrix()
    t = rng.uniform(-100.0, 100.0, 3)
    for S, s in ((np.eye(3), t), (R, np.zeros(3)), (R, t)):
        np.testing.assert_allclose(moved(shape, S, s).signed_distance(Q @ S.T + s), shape.signed_distance(Q),
                                   rtol=0, atol=1e-9)


@settings(max_examples=60)
@given(shapes(), st.integers(0, 2**32 - 1))
def test_the_gradient_is_the_unit_direction_of_increasing_distance(shape, seed):
    """Central differences (step 1e-5 mm) of the distance along each axis give the gradient
    to 1e-6, at points whose closest point is unique: within half the smallest radius of
    curvature of the surface, inside and out."""
    rng = np.random.default_rng(seed)
    if isinstance(shape, Sphere):
        reach = 0.5 * shape.radius
    else:
        reach = 0.5 * shape.radii.min() ** 2 / shape.radii.max()
    U = rng.normal(size=(40, 3))
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    X = shape.closest_point(shape.center + 30.0 * U)  # surface points all round
    Q = X + rng.uniform(-reach, reach, (40, 1)) * shape.gradient(X)
    g = shape.gradient(Q)
    np.testing.assert_allclose(np.linalg.norm(g, axis=1), 1.0, rtol=0, atol=1e-12)
    h = 1e-5
    fd = np.column_stack([(shape.signed_distance(Q + h * e) - shape.signed_distance(Q - h * e)) / (2 * h)
                          for e in np.eye(3)])
    np.testing.assert_allclose(fd, g, rtol=0, atol=1e-6)
