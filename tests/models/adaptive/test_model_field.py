"""ModelField (models.adaptive.model_field): the model shape as a distance field with its
margin, a DistanceField whose compiled kernel is its shape's distance at every point."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from models import Ellipsoid, Sphere
from models.adaptive.model_field import ModelField
from models.shapes.field import DistanceField, FieldKernel

ELLIPSOID = Ellipsoid([0.5, -1.0, 2.0], [11.5, 11.3, 10.1], Rotation.from_euler("zyx", [0.2, -0.1, 0.3]).as_matrix())
SPHERE = Sphere([0.5, -1.0, 2.0], 11.0)


@pytest.mark.parametrize("shape", [ELLIPSOID, SPHERE], ids=["ellipsoid", "sphere"])
def test_without_coverage_the_field_is_its_shape_plus_the_margin(shape):
    """The kernel's distance and gradient are the shape's bit for bit, at random points and
    on the plane of the ellipsoid's smallest axis (answered, not NaN); the uncertainty is
    the margin."""
    field = ModelField(shape, margin_mm=0.2)
    assert isinstance(field, DistanceField)
    fk = field.field_kernel()
    assert isinstance(fk, FieldKernel) and fk.params.flags.c_contiguous and fk.params.flags.writeable
    rng = np.random.default_rng(0)
    P = shape.center + rng.normal(0.0, 8.0, (50, 3))
    if isinstance(shape, Ellipsoid):
        P[0] = shape.center + shape.rotation[:, :2] @ [1.0, 0.5]  # the smallest axis is the third
    h, g, u = fk.kernel(fk.params, np.ascontiguousarray(P))
    d, g_shape = shape.signed_distance_and_gradient(P)
    assert np.array_equal(h, d) and np.array_equal(g, g_shape) and np.isfinite(h).all()
    assert np.array_equal(u, np.full(len(P), 0.2))
    assert np.array_equal(field.signed_distance(P), h) and np.array_equal(field.uncertainty(P), u)


def test_no_boundary_is_infinitely_far():
    h, g, u = ModelField.none().signed_distance_gradient_uncertainty(np.zeros((3, 3)))
    assert np.isinf(h).all() and (h > 0).all() and np.array_equal(u, np.zeros(3))


@pytest.mark.parametrize("field", [ModelField(Sphere(np.zeros(3), 12.0), 0.2), ModelField.none(), "local none"])
def test_a_non_finite_point_gets_no_answer_and_the_others_theirs(field):
    """NaN distance and gradient, +inf uncertainty at a point with a NaN or inf coordinate
    (FieldKernel's rule), whatever the field: the quadric's with its margin, and the fields
    without a boundary; the finite points' answers as alone."""
    from models.local.field import LocalField

    field = LocalField.none() if field == "local none" else field
    P = np.array([[np.nan, 0.0, 0.0], [1.0, 2.0, -3.0], [0.0, np.inf, 0.0]])
    h, g, u = field.signed_distance_gradient_uncertainty(P)
    assert np.isnan(h[[0, 2]]).all() and np.isnan(g[[0, 2]]).all() and np.isposinf(u[[0, 2]]).all()
    h1, g1, u1 = field.signed_distance_gradient_uncertainty(P[1:2])
    assert h[1] == h1[0] and u[1] == u1[0] and np.array_equal(g[1], g1[0])
