"""The compiled control step equals the reference filter (SafetyFilter on FilterSystem.inputs)
step for step, and hands every fault to it."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from eval.boundary_experiment import adversarial_starts
from eval.closed_loop import ClosedLoop, LoopConfig, ModelSnapshot
from eval.commands import AdversarialCommand
from eval.control_step import (
    _STATICS, ACTIVE_TOL, N_IDS, N_TIP_ROWS, pack_statics, remember_active, row_ids, unpack_statics, warm_guess,
)
from models.coverage import _nearest_and_worst, band_chord, fibonacci_directions
from planning import SurgeryScenario
from safety import constraints
from safety.qp import solve, warm_solution
from test_closed_loop import State, model_from_spiral_beams

QDOT_TOL = 1e-9  # rad/s: the same kernels on the same numbers; only the QP solver's own rounding differs


@pytest.fixture(scope="module")
def setup():
    scenario = SurgeryScenario()
    model, coverage = model_from_spiral_beams(scenario)
    loop = ClosedLoop(scenario)
    starts = adversarial_starts(loop, model.shape, 12, np.random.default_rng(5))
    snaps = {
        "prior": ModelSnapshot("prior", None, 0.0, np.nan, 0, coverage.view()),
        "ellipsoid": ModelSnapshot("ellipsoid", model.shape, 0.0, 0.01, model.n_points, coverage.view(model.shape)),
        "sphere": ModelSnapshot("sphere", model.sphere, 0.0, 0.3, model.n_points, coverage.view(model.sphere)),
        "no coverage": ModelSnapshot("ellipsoid", model.shape, 0.0, 0.01, model.n_points, None),
    }
    return loop, starts, snaps, State(model, coverage)


def reference(loop, t, q, command, snap, sensor_t):
    f = loop.filter
    return f.filter(f.inputs(t, q, command, snap, sensor_t)[0])


def assert_same(out, ref):
    assert out.ok == ref.ok and out.reason == ref.reason
    np.testing.assert_allclose(out.qdot, ref.qdot, rtol=0, atol=QDOT_TOL)
    assert out.active == ref.active and out.cutter_allowed == ref.cutter_allowed and out.intervened == ref.intervened
    assert out.min_clearance_mm == pytest.approx(ref.min_clearance_mm, abs=1e-12)


@settings(max_examples=120, deadline=None)
@given(start=st.integers(0, 11), kind=st.sampled_from(["prior", "ellipsoid", "sphere", "no coverage"]),
       dq=st.lists(st.floats(-0.02, 0.02), min_size=6, max_size=6),
       v=st.lists(st.floats(-25.0, 25.0), min_size=3, max_size=3), roll=st.floats(-3.0, 3.0))
def test_the_compiled_step_equals_the_reference(setup, start, kind, dq, v, roll):
    loop, starts, snaps, _ = setup
    q, command = starts[start] + np.array(dq), np.array([*v, roll])
    out, r = loop.filter.compiled.step(0.001, q, command, snaps[kind], 0.0)
    ref = reference(loop, 0.001, q, command, snaps[kind], 0.0)
    if out is None:  # left to the reference: only a fault (here: a QP the solver finds infeasible)
        assert not ref.ok and ref.reason.startswith("QP:"), ref.reason
    else:
        assert_same(out, ref)


def test_both_compiled_outcomes_occur_and_faults_go_to_the_reference(setup):
    loop, starts, snaps, _ = setup
    step, snap, q = loop.filter.compiled.step, snaps["ellipsoid"], starts[0]
    # slow: the equality optimum holds (no solver); fast toward the retina: DAQP
    assert step(0.001, q, np.array([0.1, 0.0, 0.0, 0.0]), snap, 0.0)[1].code == 0
    out = (step(0.001, q, np.array([0.0, 0.0, 60.0, 0.0]), snap, 0.0))[0]
    assert out is not None and "tip_speed" in out.active
    stale = loop.config.filter.max_sensor_age_s + 0.01
    for command, sensor_t in (([np.nan, 0.0, 0.0, 0.0], 0.0), ([500.0, 0.0, 0.0, 0.0], 0.0), ([1.0, 0.0, 0.0, 0.0], -stale)):
        out, _ = step(0.001, q, np.array(command), snap, sensor_t)
        assert out is None  # the reference says why
        assert not reference(loop, 0.001, q, np.array(command), snap, sensor_t).ok


def test_a_closed_loop_run_is_the_reference_run(setup, monkeypatch):
    # the same adversarial scenario on two fresh loops (the same sensor seed), every step
    # compiled in one and by the reference in the other: the same joint velocities at
    # every step, hence the same trajectory
    _, starts, _, state = setup
    scenario = SurgeryScenario()

    def run(loop):
        adversary = AdversarialCommand(11, scenario.eye_pose.p_WE, scenario.lens_W.center, 20.0)
        return loop.run(adversary, starts[3], 0.25, **state.kw())

    fast = run(ClosedLoop(scenario))
    by_reference = ClosedLoop(scenario)
    monkeypatch.setattr(by_reference.filter.compiled, "step", lambda *a: (None, None))
    ref = run(by_reference)
    assert fast.intervened.mean() > 0.2  # the adversary reached the boundary
    np.testing.assert_allclose(fast.qdot, ref.qdot, rtol=0, atol=QDOT_TOL)
    np.testing.assert_allclose(fast.true_clearance_mm, ref.true_clearance_mm, rtol=0, atol=1e-9)
    assert fast.ok.all() and list(fast.reasons) == list(ref.reasons)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), angle_deg=st.floats(1.0, 180.0), n=st.integers(0, 400))
def test_the_z_band_finds_what_the_full_scan_finds(seed, angle_deg, n):
    # directions sorted by z (as CoverageView keeps them); queries anywhere
    rng = np.random.default_rng(seed)
    dirs = fibonacci_directions(2000)[rng.permutation(2000)[:n]]
    dirs = np.ascontiguousarray(dirs[np.argsort(dirs[:, 2])])
    misfit = rng.uniform(0.0, 1.0, n)
    V = rng.standard_normal((8, 3))
    V /= np.linalg.norm(V, axis=1, keepdims=True)
    cos_angle = np.cos(np.radians(angle_deg))
    best_full, worst_full = _nearest_and_worst(V, dirs, misfit, cos_angle)
    best, worst = _nearest_and_worst(V, dirs, misfit, cos_angle, band_chord(np.radians(angle_deg)))
    np.testing.assert_array_equal(worst, worst_full)
    within = best_full >= cos_angle  # the nearest direction within the angle: found, exactly
    np.testing.assert_array_equal(best[within], best_full[within])
    assert np.all(best[~within] < cos_angle)


def test_trust_angle_180_trusts_everything(setup):
    loop, starts, snaps, _ = setup
    wide = ClosedLoop(loop.scenario, LoopConfig(trust_angle_deg=180.0))
    out, _ = wide.filter.compiled.step(0.001, starts[0], np.array([1.0, 0.0, 0.0, 0.0]), snaps["ellipsoid"], 0.0)
    ref = wide.filter.filter(wide.filter.inputs(0.001, starts[0], np.array([1.0, 0.0, 0.0, 0.0]), snaps["ellipsoid"], 0.0)[0])
    assert_same(out, ref)


def random_qp(seed: int, clearance_mm: float, v_cmd):
    """A filter-sized QP (6 joints, the tip speed polytope, 8 barrier rows at clearance_mm
    above a 0.5 mm h_min, 2 RCM rows) and its DAQP solution."""
    rng = np.random.default_rng(seed)
    n, k = 6, 8
    g = rng.normal(size=(k, 3))
    qp = constraints.filter_qp(
        50.0 * rng.normal(size=(3, n)), np.asarray(v_cmd, dtype=float), 1e-3, rng.normal(size=(1, n)), 0.1,
        rng.uniform(-0.1, 0.1, n), -np.ones(n), np.ones(n), 3 * np.ones(n), 10.0, 0.03, 20.0,
        tuple(f"boundary:b{i}" for i in range(k)), np.full(k, clearance_mm), g / np.linalg.norm(g, axis=1, keepdims=True),
        50.0 * rng.normal(size=(k, 3, n)), np.full(k, 0.5), 20.0, 5.0, rng.normal(size=(2, n)), np.zeros(2))
    return qp, solve(qp, "daqp")


def warm(qp, active_ids):
    ids = row_ids(np.arange(len(qp.h) - N_TIP_ROWS), len(qp.h) - N_TIP_ROWS)
    held = warm_guess(active_ids, ids, len(qp.c))
    return warm_solution(qp.H, qp.c, qp.lb, qp.ub, qp.G, qp.h, qp.A, qp.b, *held, ACTIVE_TOL), ids


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), clearance=st.floats(0.3, 3.0), v=st.lists(st.floats(-40, 40), min_size=3, max_size=3),
       guess=st.lists(st.booleans(), min_size=N_IDS, max_size=N_IDS))
def test_a_certified_warm_solution_is_the_solution(seed, clearance, v, guess):
    # whatever active set is guessed, a certified answer is the QP's unique solution (DAQP's,
    # to its rounding: 1e-9 rad/s); an uncertified one goes to the solver
    qp, ref = random_qp(seed, clearance, v)
    (certified, x), _ = warm(qp, np.array(guess))
    if certified:
        assert ref.ok
        np.testing.assert_allclose(x, ref.x, rtol=0, atol=1e-9)


def test_the_previous_active_set_certifies_the_solution():
    # the true active set (remembered from DAQP's solution) certifies it on nearly every QP
    # that needs a solver (not on the degenerate ones, with dependent active rows)
    tried = certified_count = 0
    for seed in range(60):
        qp, ref = random_qp(seed, 0.6, (15.0, -10.0, 8.0))
        if not ref.ok or not ref.active:
            continue
        tried += 1
        active_ids = np.zeros(N_IDS, dtype=bool)
        ids = row_ids(np.arange(len(qp.h) - N_TIP_ROWS), len(qp.h) - N_TIP_ROWS)
        remember_active(active_ids, ids, qp.G, qp.h, qp.lb, qp.ub, ref.x, ACTIVE_TOL)
        (certified, x), _ = warm(qp, active_ids)
        if certified:
            certified_count += 1
            np.testing.assert_allclose(x, ref.x, rtol=0, atol=1e-9)
    assert tried >= 30 and certified_count >= 0.9 * tried


def test_the_packed_constants_unpack_to_what_was_packed(setup):
    loop = setup[0]
    statics = loop.filter.compiled._statics
    parts = dict(zip(_STATICS[::2], unpack_statics(statics)))
    robot = loop.robot
    np.testing.assert_array_equal(parts["q_max"], robot.q_upper)
    np.testing.assert_array_equal(parts["S"], robot.chain.S)
    assert parts["n_shaft"] == loop.config.points.n_shaft
    np.testing.assert_array_equal(unpack_statics(statics)[-1], loop.config.points.lens_offsets_mm)
    with pytest.raises(ValueError, match="sizes"):
        pack_statics(**{**parts, "q_max": np.zeros(5), "lens_offsets": np.zeros(2)})
