"""Measured directions: covered bins, angles from the data, cheap rebuilds."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models import Sphere
from models.adaptive.coverage import DirectionCoverage, fibonacci_directions


def test_fibonacci_directions_are_unit_and_even():
    D = fibonacci_directions(4000)
    np.testing.assert_allclose(np.linalg.norm(D, axis=1), 1.0)
    assert abs(D.mean(axis=0)).max() < 1e-3


@given(st.floats(0.0, 80.0), st.floats(0.0, 2 * np.pi))
def test_the_angle_from_a_measured_cap_is_the_angle_past_its_rim(off_deg, azimuth):
    """Data over a 30 deg cap about -z: a direction at 30 + off deg from -z is off deg
    from the data, within the 2 deg bins' spacing."""
    c = np.array([1.0, 2.0, 3.0])
    cov = DirectionCoverage(c, bin_deg=2.0)
    D = fibonacci_directions(20000)
    cap = D[D[:, 2] <= -np.cos(np.radians(30.0))]
    cov.add(c + 11.0 * cap)
    th = np.radians(30.0 + off_deg)
    q = c + 5.0 * np.array([np.sin(th) * np.cos(azimuth), np.sin(th) * np.sin(azimuth), -np.cos(th)])
    angle = np.degrees(cov.view().angle_from_data_rad(q[None])[0])
    assert angle == pytest.approx(off_deg, abs=2.5)


def test_no_data_means_no_trust_and_bad_input_is_refused():
    cov = DirectionCoverage(np.zeros(3))
    assert cov.view().angle_from_data_rad(np.array([[1.0, 0.0, 0.0]]))[0] == pytest.approx(np.pi)
    cov.add(np.array([[np.nan, 0.0, 0.0]]))
    assert cov.view().n_covered == 0
    with pytest.raises(ValueError, match="bin_deg"):
        DirectionCoverage(np.zeros(3), bin_deg=0.0)


@settings(max_examples=30)
@given(st.integers(0, 2**32 - 1), st.floats(1.0, 30.0))
def test_queries_equal_a_k_d_tree_reference(seed, angle_deg):
    """The view's scans give the nearest covered direction's angle and the worst misfit
    within an angle exactly: equal to a k-d tree's answers on the same directions."""
    from scipy.spatial import cKDTree

    from models import Sphere

    rng = np.random.default_rng(seed)
    c = rng.normal(0.0, 2.0, 3)
    cov = DirectionCoverage(c)
    cov.add(c + rng.uniform(10.0, 12.0, (300, 1)) * fibonacci_directions(300) * [1.0, 1.0, -np.abs(rng.normal())])
    view = cov.view(Sphere(c, 11.5))
    Q = c + rng.normal(0.0, 5.0, (12, 3))
    U = (Q - c) / np.linalg.norm(Q - c, axis=1, keepdims=True)
    tree = cKDTree(view.sorted_directions)
    chord, _ = tree.query(U)
    np.testing.assert_allclose(view.angle_from_data_rad(Q), 2.0 * np.arcsin(chord / 2.0), atol=1e-7)
    r = 2.0 * np.sin(0.5 * np.radians(angle_deg))
    ref = [max((view.misfits_mm[j] for j in idx), default=0.0) for idx in tree.query_ball_point(U, r)]
    np.testing.assert_allclose(view.local_misfit_mm(Q, np.radians(angle_deg)), ref, atol=1e-12)


@settings(max_examples=60)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0.5, 2.0, 7.0, 30.0]))
def test_the_bin_search_equals_a_k_d_tree_on_the_fibonacci_sphere(seed, bin_deg):
    """The compiled nearest-direction search finds the k-d tree's bin for random directions,
    directions next to bins (within 1e-9) and the poles, with or without a hint (a row to
    start from: near the answer, as the bin of the A-scan before, or anywhere); and `add`
    keeps the same bins and innermost points as the k-d tree version did (scipy,
    vectorised)."""
    from scipy.spatial import cKDTree

    from models.adaptive.coverage_kernels import nearest_fibonacci

    rng = np.random.default_rng(seed)
    c = rng.normal(0.0, 3.0, 3)
    cov = DirectionCoverage(c, bin_deg=bin_deg)
    dirs = cov._dirs
    U = rng.normal(size=(200, 3))
    U = np.vstack([U, dirs[rng.integers(len(dirs), size=50)] + rng.normal(0.0, 1e-9, (50, 3)), [[0, 0, 1], [0, 0, -1]]])
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    tree = cKDTree(dirs)
    _, idx = tree.query(U)
    assert [nearest_fibonacci(u[0], u[1], u[2], dirs) for u in U] == idx.tolist()
    near = np.clip(idx + rng.integers(-3, 4, len(U)), 0, len(dirs) - 1)
    anywhere = rng.integers(len(dirs), size=len(U))
    for hints in (idx, near, anywhere):
        assert [nearest_fibonacci(u[0], u[1], u[2], dirs, h) for u, h in zip(U, hints)] == idx.tolist()

    P = c + rng.uniform(8.0, 13.0, (len(U), 1)) * U
    P[rng.integers(len(P), size=5)] = np.nan
    for batch in np.array_split(P, 7):
        cov.add(batch)
    fin = P[np.isfinite(P).all(axis=1)]
    r = np.linalg.norm(fin - c, axis=1)
    _, bins = tree.query((fin - c) / r[:, None])
    inner_r = np.full(len(dirs), np.inf)
    np.minimum.at(inner_r, bins, r)
    assert np.flatnonzero(cov._covered).tolist() == np.unique(bins).tolist() == np.flatnonzero(np.isfinite(inner_r)).tolist()
    assert cov._n_covered == len(np.unique(bins))
    np.testing.assert_array_equal(cov._inner_r, inner_r)
    hit = np.isfinite(inner_r)
    np.testing.assert_allclose(np.linalg.norm(cov._inner[hit] - c, axis=1), inner_r[hit], rtol=0, atol=0)


def _numpy_depth(shape, P):
    """inside_depth_upper_mm's formulas in NumPy (the reference for the compiled ones)."""
    if hasattr(shape, "radius"):
        return np.maximum(shape.radius - np.linalg.norm(P - shape.center, axis=1), 0.0)
    L = (P - shape.center) @ shape.rotation / shape.radii
    return np.maximum(float(shape.radii.max()) * (1.0 - np.linalg.norm(L, axis=1)), 0.0)


@pytest.mark.parametrize("kind", ["ellipsoid", "sphere"])
def test_a_rebuilt_view_holds_the_covered_bins_and_their_misfits_exactly(kind):
    """A view made for a shape holds the directions of exactly the covered bins, sorted by z,
    each with the misfit of its innermost point (inside_depth_upper_mm: its NumPy formulas,
    bit for bit), as CoverageView sorts them."""
    from models import Ellipsoid, Sphere
    from models.adaptive.coverage import CoverageView, inside_depth_upper_mm

    rng = np.random.default_rng(4)
    c = np.array([0.5, -1.0, 2.0])
    cov = DirectionCoverage(c)
    U = rng.normal(size=(400, 3))
    U[:, 2] = -np.abs(U[:, 2])
    cov.add(c + rng.uniform(10.5, 12.0, (400, 1)) * U / np.linalg.norm(U, axis=1, keepdims=True))
    a, b = 0.3, -0.2  # a rotation about z, then about x
    R = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]]) @ np.array(
        [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    shape = Ellipsoid(c, np.array([11.5, 11.4, 10.1]), R) if kind == "ellipsoid" else Sphere(c, 11.3)
    view = cov.view(shape)
    covered = cov._covered
    inner = cov._inner[covered]
    order = np.argsort(cov._dirs[covered][:, 2], kind="stable")
    assert view.n_covered == covered.sum() > 300
    np.testing.assert_array_equal(inside_depth_upper_mm(shape, inner), _numpy_depth(shape, inner))
    np.testing.assert_array_equal(view.sorted_directions, cov._dirs[covered][order])
    np.testing.assert_array_equal(view.misfits_mm, _numpy_depth(shape, inner)[order])
    sorted_here = CoverageView(c, cov._dirs[covered], _numpy_depth(shape, inner))
    np.testing.assert_array_equal(view.sorted_directions, sorted_here.sorted_directions)
    np.testing.assert_array_equal(view.misfits_mm, sorted_here.misfits_mm)
    assert view.misfits_mm.max() > 0.0  # points inside the shape: misfits to compare


@settings(max_examples=60)
@given(seed=st.integers(0, 2**32 - 1), angle_deg=st.floats(1.0, 180.0), n=st.integers(0, 400))
def test_the_z_band_finds_what_the_full_scan_finds(seed, angle_deg, n):
    # directions sorted by z (as CoverageView keeps them); queries anywhere
    from models.adaptive.coverage import band_chord
    from models.adaptive.coverage_kernels import nearest_and_worst

    rng = np.random.default_rng(seed)
    dirs = fibonacci_directions(2000)[rng.permutation(2000)[:n]]
    dirs = np.ascontiguousarray(dirs[np.argsort(dirs[:, 2])])
    misfit = rng.uniform(0.0, 1.0, n)
    V = rng.standard_normal((8, 3))
    V /= np.linalg.norm(V, axis=1, keepdims=True)
    cos_angle = np.cos(np.radians(angle_deg))
    best_full, worst_full = nearest_and_worst(V, dirs, misfit, cos_angle)
    best, worst = nearest_and_worst(V, dirs, misfit, cos_angle, band_chord(np.radians(angle_deg)))
    np.testing.assert_array_equal(worst, worst_full)
    within = best_full >= cos_angle  # the nearest direction within the angle: found, exactly
    np.testing.assert_array_equal(best[within], best_full[within])
    assert np.all(best[~within] < cos_angle)


def test_model_field_trust_is_the_two_queries():
    """ModelField.trust (the compiled rule the filter's field and its log use): trusted
    within the trust angle of a covered direction, the misfit the largest within the
    misfit angle, as angle_from_data_rad and local_misfit_mm answer them."""
    from models.adaptive.coverage import band_chord
    from models.adaptive.model_field import ModelField

    rng = np.random.default_rng(4)
    cov = DirectionCoverage(np.zeros(3))
    P = rng.normal(size=(400, 3))
    P = 11.0 * P / np.linalg.norm(P, axis=1, keepdims=True)
    cov.add(P[P[:, 2] < 0])
    shape = Sphere(np.zeros(3), 11.2)
    view = cov.view(shape)  # misfits: how deep inside the sphere each bin's points lie
    Q = rng.normal(size=(40, 3)) * 5.0
    for trust, misfit_angle in np.radians([(10.0, 10.0), (3.0, 10.0), (40.0, 5.0)]):
        chord = max(band_chord(trust), band_chord(misfit_angle))
        field = ModelField(shape, 0.0, view, trust_angle_rad=trust, misfit_angle_rad=misfit_angle, band_chord=chord)
        trusted, misfit = field.trust(Q)
        np.testing.assert_array_equal(trusted, view.angle_from_data_rad(Q) <= trust)
        np.testing.assert_allclose(misfit, view.local_misfit_mm(Q, misfit_angle), rtol=0, atol=1e-12)


def test_the_misfit_is_of_the_shape_asked_for_not_of_an_earlier_one():
    """A sphere refitted between two views (same kind, no new bins) gets its own misfits:
    a point measured 0.5 mm inside the retina of an 11 mm sphere lies 0.5 mm inside it,
    and 0.5 - 0.6 < 0 (none) inside the sphere refitted 0.6 mm smaller."""
    c = np.array([1.0, -2.0, 3.0])
    cov = DirectionCoverage(c)
    cov.add(c + 10.5 * np.array([[0.0, 0.0, -1.0]]))
    assert cov.view(Sphere(c, 11.0)).local_misfit_mm(c + np.array([[0.0, 0.0, -10.0]]), np.radians(5.0))[0] == \
        pytest.approx(0.5, abs=1e-9)
    assert cov.view(Sphere(c, 10.4)).local_misfit_mm(c + np.array([[0.0, 0.0, -10.0]]), np.radians(5.0))[0] == 0.0
    assert cov.view(Sphere(c, 11.5)).local_misfit_mm(c + np.array([[0.0, 0.0, -10.0]]), np.radians(5.0))[0] == \
        pytest.approx(1.0, abs=1e-9)
