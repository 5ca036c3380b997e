"""The joint trajectory's waypoint velocities (planning.scan.waypoint_velocities): no
overshoot where a joint's waypoints run monotone, and one direction for all joints where
the waypoints do (the RCM-constrained motion's velocity to first order)."""
from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pydrake.trajectories import PiecewisePolynomial

from planning.scan import waypoint_velocities


def _curve(t, Q):
    return PiecewisePolynomial.CubicHermite(t, Q.T, waypoint_velocities(t, Q).T)


@settings(max_examples=60)
@given(st.integers(2, 12), st.integers(0, 2**32 - 1))
def test_a_joint_stays_within_its_waypoints_where_they_run_monotone(n, seed):
    rng = np.random.default_rng(seed)
    t = np.concatenate([[0.0], np.cumsum(rng.uniform(0.001, 1.0, n - 1))])
    # steps of random size and sign, some runs monotone, with very uneven spacing in time
    Q = np.cumsum(rng.normal(0.0, 1.0, (n, 6)) * rng.choice([0.01, 1.0, 10.0], (n, 6)), axis=0)
    curve = _curve(t, Q)
    s = np.diff(Q, axis=0)
    for i in range(n - 1):
        x = curve.vector_values(np.linspace(t[i], t[i + 1], 41)).T
        lo, hi = np.minimum(Q[i], Q[i + 1]), np.maximum(Q[i], Q[i + 1])
        # the segment's neighbours agree with it in sign (or it touches an end, at rest)
        monotone = np.ones(6, bool)
        if i > 0:
            monotone &= s[i - 1] * s[i] > 0
        if i < n - 2:
            monotone &= s[i + 1] * s[i] > 0
        tol = 1e-9 * (1.0 + np.abs(Q).max())
        assert np.all(x[:, monotone] >= lo[monotone] - tol) and np.all(x[:, monotone] <= hi[monotone] + tol)
    np.testing.assert_allclose(curve.vector_values(t).T, Q, atol=1e-9)
    np.testing.assert_array_equal(waypoint_velocities(t, Q)[[0, -1]], 0.0)  # at rest at both ends


@settings(max_examples=40)
@given(st.integers(3, 12), st.integers(0, 2**32 - 1))
def test_waypoints_on_a_line_in_joint_space_move_along_it(n, seed):
    """Waypoints q0 + u f_i (f rising, unevenly in time): every velocity is a positive
    multiple of u, limited or not. (That the planned paths keep the RCM between waypoints,
    which per-joint limiting does not, is tested on a whole plan: test_peripheral.)"""
    rng = np.random.default_rng(seed)
    t = np.concatenate([[0.0], np.cumsum(rng.uniform(0.01, 1.0, n - 1))])
    u = rng.normal(size=6)
    f = np.cumsum(rng.uniform(0.01, 2.0, n))
    V = waypoint_velocities(t, u * f[:, None])
    np.testing.assert_allclose(V - np.outer(V @ u / (u @ u), u), 0.0, atol=1e-9 * np.abs(V).max() + 1e-15)
    assert np.all(V[1:-1] @ u > 0.0)


@pytest.mark.parametrize("t, Q, words", [
    ([0.0, 1.0, 1.0, 2.0], np.zeros((4, 6)), "increase strictly"),  # a repeated time: no secant there
    ([0.0, 2.0, 1.0], np.zeros((3, 6)), "increase strictly"),
    ([0.0, np.nan, 2.0], np.zeros((3, 6)), "finite"),
    ([0.0, 1.0], np.full((2, 6), np.inf), "finite"),
    ([0.0, 1.0, 2.0], np.zeros((3, 5)), "Q (N, 6)"),
    ([0.0], np.zeros((1, 6)), "N >= 2"),
])
def test_waypoints_the_curve_cannot_pass_are_refused(t, Q, words):
    with pytest.raises(ValueError, match=re.escape(words)):
        waypoint_velocities(t, Q)
