"""The search adversary's scenario parameters: what a theta commands."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from eval.experiments.boundary import START_DEPTH_MM
from eval.experiments.search_adversary import DIMENSIONS, MAX_ROLL_RATE, ParametricCommand, start_of


@settings(max_examples=50)
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


def test_the_search_restarts_out_of_a_broad_basin_into_a_narrow_deeper_one():
    """A broad bowl (minimum 1 at the origin, where the search starts) and a narrow well
    (minimum 0 at b, ~4 % of the initial Gaussian's mass): the cross-entropy method settles
    in the bowl within a few generations; its restarts draw from the initial Gaussian again
    (140 broad draws in a budget of 2,000 miss the well with probability ~0.2 %)."""
    from eval.experiments.search_adversary import minimise

    b, r = np.array([2.0, 0.0]), 0.8

    def objective(x, k):
        d2 = float(np.sum((x - b) ** 2))
        return d2 / r ** 2 if d2 < r ** 2 else 1.0 + 0.1 * float(np.sum(x ** 2))

    calls = []
    score, theta, k, restarts = minimise(lambda x, k: calls.append(k) or objective(x, k), np.zeros(2), 2000, seed=3)
    assert calls == list(range(2000))  # the budget, each evaluation numbered
    assert restarts >= 2 and score < 0.05 and np.linalg.norm(theta - b) < 0.2 * r
    assert objective(theta, k) == score


@pytest.mark.slow
def test_the_islands_give_the_same_worst_scenario_on_any_workers_and_it_replays(monkeypatch):
    """Two islands of 3 simulations: one process and two worker processes find the same
    clearances and worst scenario, and run_theta with its theta and sensor seed reaches
    exactly its clearance again."""
    from eval.closed_loop import ClosedLoop
    from eval.experiments import search_adversary
    from eval.experiments.campaign import Workers
    from planning import SurgeryScenario
    from test_closed_loop import model_from_spiral_beams

    monkeypatch.setattr(search_adversary, "ISLAND_BUDGET", 3)
    scenario = SurgeryScenario()
    model, coverage = model_from_spiral_beams(scenario)
    loop = ClosedLoop(scenario)
    one, two = (search_adversary.cross_entropy_search(loop, model, coverage, 6, 5, 0.1, workers=Workers(jobs=j))
                for j in (1, 2))
    assert search_adversary.islands(6) == [3, 3] and len(one.clearances) >= 2
    assert one.clearances == two.clearances and one.worst_clearance_mm == two.worst_clearance_mm
    assert one.worst_sensor_seed == two.worst_sensor_seed and one.worst_sensor_seed[:2] == [5, one.worst_sensor_seed[1]]
    run = search_adversary.run_theta(loop, model, coverage, one.worst_theta, 0.1, one.worst_sensor_seed)
    assert float(run.true_clearance_mm.min()) == one.worst_clearance_mm
