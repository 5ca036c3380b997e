"""Measured directions: covered bins, angles from the data, cheap rebuilds."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from models.coverage import DirectionCoverage, fibonacci_directions


def test_fibonacci_directions_are_unit_and_even():
    D = fibonacci_directions(4000)
    np.testing.assert_allclose(np.linalg.norm(D, axis=1), 1.0)
    assert abs(D.mean(axis=0)).max() < 1e-3


@settings(deadline=None)  # the first call loads the compiled query
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


@settings(deadline=None, max_examples=30)
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
    tree = cKDTree(view._dirs)
    chord, _ = tree.query(U)
    np.testing.assert_allclose(view.angle_from_data_rad(Q), 2.0 * np.arcsin(chord / 2.0), atol=1e-7)
    r = 2.0 * np.sin(0.5 * np.radians(angle_deg))
    ref = [max((view._misfit[j] for j in idx), default=0.0) for idx in tree.query_ball_point(U, r)]
    np.testing.assert_allclose(view.local_misfit_mm(Q, np.radians(angle_deg)), ref, atol=1e-12)
