"""ScanRange: the exact diameter of a growing point set (the paper's scan range).

Reference: scipy's pdist (every pair). The incremental form uses |p - q|^2 = |p|^2 + |q|^2
- 2 p.q about the first point; for clouds of extent D the cancellation error in the
distance is ~1e-16 D^2 / d_max ~ 1e-14 mm here: 1e-9 mm leaves a wide margin.
"""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.distance import pdist

from models.adaptive.scan_range import ScanRange

TOL_MM = 1e-9


@settings(max_examples=40)
@given(
    st.integers(2, 400),
    st.floats(0.1, 30.0),
    st.lists(st.floats(-300.0, 300.0), min_size=3, max_size=3),
    st.integers(0, 2**32 - 1),
    st.data(),
)
def test_diameter_equals_brute_force_max_pairwise_distance_for_any_batching(n, extent, offset, seed, data):
    P = np.random.default_rng(seed).normal(0.0, extent, (n, 3)) + offset
    cuts = sorted(data.draw(st.lists(st.integers(1, n - 1), max_size=10, unique=True))) if n > 1 else []
    sr = ScanRange(capacity=16)  # small capacity: the buffers must grow
    diameters = [sr.add(chunk) for chunk in np.split(P, cuts)]
    assert sr.n_points == n
    assert sr.diameter_mm == float(diameters[-1])
    np.testing.assert_allclose(sr.diameter_mm, pdist(P).max(), rtol=0, atol=TOL_MM)
    assert np.all(np.diff(diameters) >= 0.0)  # a diameter never shrinks


def test_single_point_and_repeated_points_have_zero_range():
    sr = ScanRange()
    assert sr.add(np.array([[1.0, 2.0, 3.0]])) == 0.0
    assert sr.add(np.tile([[1.0, 2.0, 3.0]], (5, 1))) == 0.0


def test_spiral_like_growth_matches_every_prefix():
    t = np.linspace(0, 12 * np.pi, 600)
    P = np.column_stack([0.3 * t * np.cos(t), 0.3 * t * np.sin(t), -10.0 + 0.01 * t])
    sr = ScanRange()
    for k in range(len(P)):
        sr.add(P[k : k + 1])
        if k % 60 == 59:
            np.testing.assert_allclose(sr.diameter_mm, pdist(P[: k + 1]).max(), rtol=0, atol=TOL_MM)


def test_one_point_at_a_time_the_buffers_grow_without_a_copy_of_every_point(monkeypatch):
    """Single points from capacity 64 to 5,000 points (each doubling begun at half full): no reserve copies more
    than max(MIN_MOVE, MOVE_PER_POINT) rows, the whole buffer is never concatenated, and
    the diameter stays exact through every takeover."""
    moves = []
    move = ScanRange._move

    def watched(self, upto):
        moves.append(upto - self._moved)
        move(self, upto)

    def no_concatenate(*args, **kwargs):
        raise AssertionError("the buffers were copied at once")

    monkeypatch.setattr(ScanRange, "_move", watched)
    monkeypatch.setattr("models.adaptive.scan_range.np.concatenate", no_concatenate)
    t = np.linspace(0, 40 * np.pi, 5000)
    P = np.column_stack([0.1 * t * np.cos(t), 0.1 * t * np.sin(t), -10.0 + 0.01 * t])
    sr = ScanRange(capacity=64)
    capacities = {len(sr.X)}
    for k in range(len(P)):
        sr.add(P[k:k + 1])
        capacities.add(len(sr.X))
        if k + 1 in (64, 65, 128, 129, 1000, 4096, 4097, 5000):
            np.testing.assert_allclose(sr.diameter_mm, pdist(P[:k + 1]).max(), rtol=0, atol=TOL_MM)
    assert sorted(capacities) == [64 * 2**i for i in range(len(capacities))] and max(capacities) >= len(P)
    assert max(moves) <= max(ScanRange.MIN_MOVE, ScanRange.MOVE_PER_POINT)
