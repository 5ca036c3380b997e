"""Campaigns spread over workers give the campaign of one process: each scenario's
randomness comes from its index, so the figures are the same to the bit whatever the
number of workers or the order the scenarios ran in."""
from __future__ import annotations

import time

import numpy as np
import pytest

from eval.closed_loop import ClosedLoop
from eval.experiments.boundary import AdversarialScenario, run_campaign
from eval.experiments.campaign import (BATCHES_PER_WORKER, LOCAL_RAY, MAX_BATCH, Workers, WorkersError, batches, connect_ray,
                                      run_tasks, scenario_seed)
from planning import SurgeryScenario
from test_closed_loop import model_from_spiral_beams

SAME = 1e-12  # figures that must be identical (a float printed and read back differs by more)
FIGURES = ("violations", "contacts", "min_true_clearance_mm", "lens_violations", "intervention_fraction",
           "tracking_rmse_mm_s", "failsafe_stops", "max_rcm_error_um", "free_tracking_error_p99")


@pytest.fixture(scope="module")
def loop_and_model():
    scenario = SurgeryScenario()
    model, coverage = model_from_spiral_beams(scenario)
    return ClosedLoop(scenario), model, coverage


def _figures(campaign) -> dict:
    s = campaign.summary()
    return {k: s[k] for k in FIGURES}


def _assert_same(a: dict, b: dict) -> None:
    for k in FIGURES:
        assert a[k] == pytest.approx(b[k], abs=SAME, rel=0), k


@pytest.mark.slow
def test_one_and_two_workers_give_the_same_campaign(loop_and_model):
    loop, model, coverage = loop_and_model
    one = run_campaign(loop, model, coverage, 6, seed=5, duration_s=0.2, workers=Workers(jobs=1))
    two = run_campaign(loop, model, coverage, 6, seed=5, duration_s=0.2, workers=Workers(jobs=2))
    _assert_same(_figures(one), _figures(two))
    np.testing.assert_allclose(two.min_clearance_per_run, one.min_clearance_per_run, rtol=0, atol=SAME)
    for a, b in zip(one.runs, two.runs):
        np.testing.assert_allclose(b.q, a.q, rtol=0, atol=SAME)


def test_a_scenario_does_not_depend_on_the_scenarios_run_before_it(loop_and_model):
    loop, model, coverage = loop_and_model
    task = AdversarialScenario(model, coverage, seed=2, duration_s=0.1)
    alone = task(loop, 3)
    task(loop, 0)  # another scenario in between: the sensor's and adversary's draws are per scenario
    again = run_tasks(loop, task, [1, 3])[1]
    np.testing.assert_array_equal(again.q, alone.q)
    np.testing.assert_array_equal(again.true_clearance_mm, alone.true_clearance_mm)


def test_scenario_seeds_are_per_index_and_independent_of_the_campaign_size():
    a, b = scenario_seed(7, 3), scenario_seed(7, 3)
    assert a.generate_state(4).tolist() == b.generate_state(4).tolist()
    assert scenario_seed(7, 4).generate_state(4).tolist() != a.generate_state(4).tolist()
    assert scenario_seed(8, 3).generate_state(4).tolist() != a.generate_state(4).tolist()


@pytest.mark.parametrize("n, workers", [(1, 1), (7, 2), (1000, 2), (100_000, 64)])
def test_batches_cover_every_index_once_in_order(n, workers):
    parts = batches(list(range(n)), workers)
    assert [i for p in parts for i in p] == list(range(n))
    assert max(len(p) for p in parts) <= MAX_BATCH
    assert len(parts) >= min(n, BATCHES_PER_WORKER * workers) or max(len(p) for p in parts) == MAX_BATCH


@pytest.mark.parametrize("jobs", [0, -1, 1.5, True])
def test_workers_refuse_a_job_count_below_one(jobs):
    with pytest.raises(ValueError, match="jobs"):
        Workers(jobs=jobs)


@pytest.mark.slow
def test_a_local_ray_instance_with_two_workers_gives_the_same_campaign(loop_and_model):
    ray = pytest.importorskip("ray")
    loop, model, coverage = loop_and_model
    try:
        on_ray = run_campaign(loop, model, coverage, 4, seed=9, duration_s=0.1, workers=Workers(jobs=2, ray=LOCAL_RAY))
    finally:
        ray.shutdown()
    here = run_campaign(loop, model, coverage, 4, seed=9, duration_s=0.1, workers=Workers(jobs=1))
    _assert_same(_figures(here), _figures(on_ray))
    np.testing.assert_allclose(on_ray.min_clearance_per_run, here.min_clearance_per_run, rtol=0, atol=SAME)


def test_an_unreachable_ray_address_is_a_one_line_error_within_30_s(tmp_path, capsys):
    from eval.cli import main

    out = tmp_path / "never"
    t0 = time.monotonic()
    code = main(["boundary", "--ray", "127.0.0.1:1", "--scenarios", "2", "--out", str(out)])  # port 1: nothing listens
    err = capsys.readouterr().err
    assert code == 2 and time.monotonic() - t0 < 30.0
    assert err.count("\n") == 1 and "--ray 127.0.0.1:1" in err, err
    assert not out.exists()


@pytest.mark.parametrize("address", ["nohost", "host:port", ":80"])
def test_a_malformed_ray_address_is_refused(address):
    with pytest.raises(WorkersError, match="host:port"):
        connect_ray(Workers(ray=address))
