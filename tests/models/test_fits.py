"""Sphere and ellipsoid fits: exact recovery, invariance, incremental = batch, degeneracy."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from models import Ellipsoid, IncrementalEllipsoidFit, Sphere, SphereKalmanFilter, fit_ellipsoid, fit_sphere

radii_st = st.lists(st.floats(6.0, 13.0), min_size=3, max_size=3).filter(lambda r: max(r) <= 1.9 * min(r))
center_st = st.lists(st.floats(-300.0, 300.0), min_size=3, max_size=3)


def _patch(e: Ellipsoid, n_theta=30, n_phi=40):
    """Points over the posterior two thirds of e (a scan never sees the front)."""
    return e.sample_surface(n_theta, n_phi, z_max=0.3 * e.radii[2])


def _axes_match(R1, R2, tol):
    """Columns equal up to sign and order."""
    M = np.abs(R1.T @ R2)
    return np.allclose(np.sort(M.max(axis=0)), 1.0, atol=tol) and np.allclose(np.sort(M.max(axis=1)), 1.0, atol=tol)


@settings(max_examples=40, deadline=None)
@given(radii_st, center_st, st.integers(0, 2**31 - 1))
def test_noise_free_ellipsoid_is_recovered(radii, center, seed):
    e = Ellipsoid(center, radii, Rotation.random(random_state=seed).as_matrix())
    f = fit_ellipsoid(_patch(e))
    np.testing.assert_allclose(f.center, e.center, atol=1e-6)
    np.testing.assert_allclose(np.sort(f.radii), np.sort(e.radii), atol=1e-6)
    r = np.sort(radii)
    if np.min(np.diff(r)) > 0.2:  # axes are only defined for distinct radii
        order_f, order_e = np.argsort(f.radii), np.argsort(e.radii)
        assert _axes_match(f.rotation[:, order_f], e.rotation[:, order_e], 1e-6)


@settings(max_examples=40, deadline=None)
@given(st.floats(5.0, 15.0), center_st)
def test_noise_free_sphere_is_recovered(radius, center):
    s = Sphere(center, radius)
    P = s.sample_surface(20, 30, z_max=0.0)
    f = fit_sphere(P)
    np.testing.assert_allclose(f.center, s.center, atol=1e-6)
    assert f.radius == pytest.approx(radius, abs=1e-6)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**31 - 1), center_st)
def test_fits_are_invariant_to_rigid_motion(seed, shift):
    rng = np.random.default_rng(seed)
    P = _patch(Ellipsoid([0, 0, 0], [11.4, 11.3, 10.1])) + rng.normal(0, 0.02, (1200, 3))
    R = Rotation.random(random_state=seed).as_matrix()
    t = np.asarray(shift)
    e0, e1 = fit_ellipsoid(P), fit_ellipsoid(P @ R.T + t)
    np.testing.assert_allclose(e1.center, R @ e0.center + t, atol=1e-6)
    np.testing.assert_allclose(np.sort(e1.radii), np.sort(e0.radii), atol=1e-6)
    s0, s1 = fit_sphere(P), fit_sphere(P @ R.T + t)
    np.testing.assert_allclose(s1.center, R @ s0.center + t, atol=1e-6)
    assert s1.radius == pytest.approx(s0.radius, abs=1e-6)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.integers(1, 300), min_size=1, max_size=8), st.integers(0, 1000))
def test_incremental_fits_equal_batch_fits_however_the_points_come(batches, seed):
    rng = np.random.default_rng(seed)
    P = _patch(Ellipsoid([100, 0, 50], [11.4, 11.3, 10.1])) + rng.normal(0, 0.02, (1200, 3))
    inc, kf = IncrementalEllipsoidFit(), SphereKalmanFilter()
    start = 0
    for size in batches + [len(P)]:
        chunk = P[start:start + size]
        if size == 1 or len(chunk) == 0:
            for p in chunk:
                inc.add(p[None]), kf.update(p)
        else:
            inc.add(chunk), kf.update(chunk)
        start += size
        if start >= len(P):
            break
    e, s = fit_ellipsoid(P), fit_sphere(P)
    fit = inc.fit()
    np.testing.assert_allclose(fit.center, e.center, atol=1e-6)
    np.testing.assert_allclose(np.sort(fit.radii), np.sort(e.radii), atol=1e-6)
    np.testing.assert_allclose(kf.sphere.center, s.center, atol=1e-6)
    assert kf.sphere.radius == pytest.approx(s.radius, abs=1e-6)


def test_degenerate_data_is_reported_and_the_last_fit_kept(monkeypatch):
    inc = IncrementalEllipsoidFit()
    inc.add(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]))
    assert inc.fit().status == "too_few_points"
    line = np.outer(np.arange(20.0), [1.0, 2.0, 3.0])
    plane = np.column_stack([np.random.default_rng(0).normal(size=(30, 2)), np.zeros(30)])
    for P, reason in ((line, "collinear"), (plane, "coplanar")):
        with pytest.raises(ValueError, match=reason):
            fit_ellipsoid(P)
        f = IncrementalEllipsoidFit()
        f.add(P)
        assert f.fit().status == reason and f.last_ok is None
    with pytest.raises(ValueError, match="too_few_points"):
        fit_ellipsoid(np.random.default_rng(1).normal(size=(8, 3)))
    with pytest.raises(ValueError, match="coplanar"):
        fit_sphere(plane)
    # a good fit survives a later failure
    good = IncrementalEllipsoidFit()
    good.add(_patch(Ellipsoid([0, 0, 0], [11.4, 11.3, 10.1])))
    first = good.fit()
    import models.ellipsoid_fit as ef

    monkeypatch.setattr(ef, "solve_scatter", lambda S: None)  # the best quadric is not an ellipsoid...
    assert good.fit().status == "not_ellipsoid"
    assert good.last_ok is first  # ...and the previous answer is kept


def test_fit_inputs_are_validated():
    with pytest.raises(ValueError, match="P"):
        fit_ellipsoid(np.zeros((20, 2)))
    with pytest.raises(ValueError, match="P"):
        fit_sphere([[0, 0, np.nan]] * 5)
