"""The search adversary's scenario parameters: what a theta commands."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from eval.experiments.boundary import START_DEPTH_MM
from eval.experiments.search_adversary import DIMENSIONS, MAX_ROLL_RATE, ParametricCommand, start_of


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-50, 50), min_size=DIMENSIONS, max_size=DIMENSIONS))
def test_any_theta_commands_within_the_speed_and_roll_limits_and_starts_inside(theta):
    u, depth = start_of(theta)
    assert abs(np.linalg.norm(u) - 1.0) < 1e-9 or np.linalg.norm(theta[:3]) < 1e-9
    assert START_DEPTH_MM[0] <= depth <= START_DEPTH_MM[1]
    command = ParametricCommand(theta, np.zeros(3), 20.0)
    p = np.array([3.0, -2.0, -8.0])
    for k in range(1000):  # 1 s: every segment (at most 5 x 0.2 s)
        v, roll = command(k * 1e-3, p, np.zeros(6))
        assert np.linalg.norm(v) <= 20.0 + 1e-9 and abs(roll) <= MAX_ROLL_RATE
        p = p + 1e-3 * v


def test_a_segment_pointing_outward_pushes_away_from_the_centre():
    theta = np.zeros(DIMENSIONS)
    theta[4:10] = [1.0, 0.0, 0.0, 10.0, 0.0, 0.0]  # first segment: along the outward normal, at full speed
    v, _ = ParametricCommand(theta, np.zeros(3), 20.0)(0.0, np.array([0.0, 0.0, -8.0]), np.zeros(6))
    np.testing.assert_allclose(v, [0.0, 0.0, -20.0], atol=1e-3)
