"""The step's warm start: a remembered active set, certified by the KKT conditions, gives
the QP's unique solution (DAQP's, to its rounding) and nothing else."""
from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from safety import step_core as core
from safety.qp import solve, warm_solution
from test_qp import random_filter_qp

N_ROWS = 26 + 8  # random_filter_qp's inequality rows


def finish(qp, active):
    ids = np.arange(len(qp.h), dtype=np.int64)
    return core.finish(qp.H, qp.c, qp.lb, qp.ub, qp.G, qp.h, qp.A, qp.b, ids, active, True,
                       np.zeros(len(qp.h), dtype=np.int64))


@settings(max_examples=80)
@given(seed=st.integers(0, 2**32 - 1), clearance=st.floats(0.3, 3.0), v=st.lists(st.floats(-40, 40), min_size=3, max_size=3),
       guess=st.lists(st.booleans(), min_size=N_ROWS + 12, max_size=N_ROWS + 12))
def test_a_certified_warm_solution_is_the_solution(seed, clearance, v, guess):
    # whatever active set is guessed, an answer the step gives without the solver is the
    # QP's unique solution; otherwise it asks for the solver
    qp = random_filter_qp(seed, clearance, v)
    ref = solve(qp, "daqp")
    code, x, _ = finish(qp, np.array(guess))
    if code == core.STEP_OPTIMAL:
        assert ref.ok
        np.testing.assert_allclose(x, ref.x, rtol=0, atol=1e-9)
    else:
        assert code == core.STEP_NEEDS_SOLVER


def solved_with_active_sets(seeds):
    """(qp, DAQP's result, its active set as the step remembers it) for the filter-shaped
    QPs of `seeds` whose solution has an active row."""
    for seed in seeds:
        qp = random_filter_qp(seed, 0.6, (15.0, -10.0, 8.0))
        ref = solve(qp, "daqp")
        if not ref.ok or not ref.active:
            continue
        active = np.zeros(N_ROWS + 12, dtype=bool)
        core.remember_active(active, np.arange(len(qp.h), dtype=np.int64), qp.G, qp.h, qp.lb, qp.ub, ref.x,
                             core.ACTIVE_TOL, np.zeros(len(qp.h), dtype=np.int64))
        yield qp, ref, active


def test_the_previous_active_set_certifies_the_solution():
    # the true active set (remembered from DAQP's solution) certifies it on nearly every QP
    # that needs a solver (not on the degenerate ones, with dependent active rows)
    tried = certified = 0
    for qp, ref, active in solved_with_active_sets(range(60)):
        tried += 1
        code, x, _ = finish(qp, active)
        if code == core.STEP_OPTIMAL:
            certified += 1
            np.testing.assert_allclose(x, ref.x, rtol=0, atol=1e-9)
    assert tried >= 30 and certified >= 0.9 * tried


def test_the_solution_one_change_from_the_previous_active_set_needs_no_solver():
    # a step's active set mostly differs from the previous step's by one constraint: with
    # one of the solution's active rows released from the guess, the held set alone is no
    # certificate (the released row is violated), and the changes reach the solution on
    # most QPs (here 2 to 4 rows active on random Jacobians, harder than a filter step's:
    # 60 of these 80; in the boundary campaign 97 % of the steps the previous set did not
    # certify), each time DAQP's answer
    tried = reached = 0
    for qp, ref, active in solved_with_active_sets(range(80)):
        active[np.flatnonzero(active)[0]] = False
        n = len(qp.c)
        held_alone, _ = warm_solution(qp.H, qp.c, qp.lb, qp.ub, qp.G, qp.h, qp.A, qp.b, active[:N_ROWS],
                                      active[N_ROWS:N_ROWS + n].copy(), active[N_ROWS + n:].copy(), core.ACTIVE_TOL)
        if held_alone:  # the released row was only weakly active
            continue
        tried += 1
        code, x, _ = finish(qp, active)
        if code == core.STEP_OPTIMAL:
            reached += 1
            np.testing.assert_allclose(x, ref.x, rtol=0, atol=1e-9)
    assert tried >= 40 and reached >= 2 / 3 * tried
