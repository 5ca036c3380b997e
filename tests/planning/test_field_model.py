"""The planner's view of the filter's field: h - k u, the retina's ray cast and normals,
and the cells whose target the uncertainty puts within the boundary."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models import Ellipsoid, Sphere
from models.adaptive.model_field import ModelField
from models.local.field import LocalField
from planning.field_model import FieldModel, least_uncertainty_mm, retina_of
from planning.peripheral import BandSpec, band_surface, cell_reach


def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@settings(max_examples=30)
@given(st.floats(0.0, 2.0), st.floats(0.0, 4.0), st.lists(st.floats(-1, 1), min_size=3, max_size=3))
def test_a_sphere_with_a_margin_grants_its_distance_less_k_times_the_margin(margin, k, v):
    """ModelField(sphere, margin) has u = margin everywhere (no coverage): the granted
    clearance is the sphere's distance - k margin; the ray from the centre meets it at the radius."""
    if np.linalg.norm(v) < 1e-3:
        v = [1.0, 0.0, 0.0]
    sphere = Sphere(np.array([1.0, -2.0, 3.0]), 11.0)
    model = FieldModel(ModelField(sphere, margin), k, "sphere")
    P = sphere.center + np.outer([0.0, 5.0, 10.5], _unit(v))
    np.testing.assert_allclose(model.signed_distance(P), sphere.signed_distance(P) - k * margin, atol=1e-9)
    np.testing.assert_allclose(retina_of(model).signed_distance(P), sphere.signed_distance(P), atol=1e-9)
    assert model.ray_cast(sphere.center[None], _unit(v)[None])[0] == pytest.approx(11.0, abs=1e-9)


def test_the_ray_cast_of_an_exact_local_field_is_the_ellipsoid_s():
    """LocalField.exact (sd 0) of an eye-sized ellipsoid: rays from the centre meet the
    retina where the ellipsoid's own ray cast does, to the bisection's 1e-9 mm."""
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    ell = Ellipsoid(np.array([0.5, 0.0, -1.0]), np.array([11.5, 10.2, 12.0]), R)
    model = FieldModel(LocalField.exact(ell, ell.center), 3.0, "prior")
    U = _unit(np.random.default_rng(3).normal(size=(50, 3)))
    O = np.repeat(ell.center[None], 50, axis=0)
    np.testing.assert_allclose(model.ray_cast(O, U), ell.ray_cast(O, U), atol=1e-6)
    assert np.all(np.isnan(model.ray_cast(O + 30.0 * U, U)))  # starting outside: no hit


def test_a_bound_grants_its_clearance_while_the_surface_stays_the_field_s():
    """FieldModel(field, k, bound=b): the clearance is b's h - k u (the filter's barrier),
    the retina, its normals and u are the field's. A model sphere of 11 mm with u = 1 mm
    under a bound that is the same sphere with u = 0.25 mm: the clearance gains 0.75 k mm,
    the ray from the centre still meets the model at 11 mm."""
    sphere = Sphere(np.array([1.0, -2.0, 3.0]), 11.0)
    model = FieldModel(ModelField(sphere, 1.0), 2.0, "sphere", bound=ModelField(sphere, 0.25))
    P = sphere.center + np.outer([0.0, 5.0, 10.5], _unit([0.3, -1.0, 0.2]))
    np.testing.assert_allclose(model.signed_distance(P), sphere.signed_distance(P) - 0.5, atol=1e-9)
    np.testing.assert_allclose(model.uncertainty(P), 1.0, atol=1e-12)
    np.testing.assert_allclose(retina_of(model).signed_distance(P), sphere.signed_distance(P), atol=1e-9)
    np.testing.assert_allclose(model.gradient(P[1:]), sphere.gradient(P[1:]), atol=1e-9)
    assert model.ray_cast(sphere.center[None], _unit([0.3, -1.0, 0.2])[None])[0] == pytest.approx(11.0, abs=1e-9)


def test_cells_whose_target_the_uncertainty_reaches_are_uncertain(setup):
    """The surgery eye's ellipsoid as a ModelField with margin m, k = 1: a target 1 mm inside
    it is granted 1 - m mm; against 0.564 mm + 0.2 mm it is "uncertain" exactly when m > 0.236 mm."""
    scenario, robot, _ = setup
    eye = scenario.eye
    ell = Ellipsoid(eye.pose.p_WE, eye.radii, eye.pose.R_WE)
    spec = BandSpec(standoff_mm=1.0, boundary_mm=0.564)
    U = _unit((eye.pose.R_WE @ np.array([[1.0, 0.3, 0.2], [-0.4, 1.0, 0.1], [0.2, -1.0, 0.3]]).T).T)
    S = eye.pose.p_WE + ell.ray_cast(np.repeat(eye.pose.p_WE[None], 3, axis=0), U)[:, None] * U
    N = ell.gradient(S)
    T = S + spec.standoff_mm * N
    for m, uncertain in ((0.2, False), (0.3, True)):
        reasons, _, _ = cell_reach(robot, scenario, T, N, spec, model=FieldModel(ModelField(ell, m), 1.0))
        assert (reasons == "uncertain").all() == uncertain and ((reasons == "uncertain").any() == uncertain)
    fm = FieldModel(ModelField(ell, 0.3), 2.0)
    assert least_uncertainty_mm(fm, band_surface(fm, scenario.eye_pose, spec), spec.standoff_mm) == pytest.approx(0.6)
    assert least_uncertainty_mm(ell, band_surface(ell, scenario.eye_pose, spec), spec.standoff_mm) == 0.0

