"""Safety-filter QP: solve time per qpsolvers backend on a filter-sized problem
(6 joints, 8 boundary rows, 26 tip-speed rows, 2 RCM rows, joint bounds)."""
from __future__ import annotations

import numpy as np
import qpsolvers

from bench.timing import summary_us, time_calls_us
from safety import constraints
from safety.qp import solve


def filter_sized_qp(seed: int = 0):
    """A filter-sized DenseQP with random Meca500-like lever arms (50 mm/rad)."""
    rng = np.random.default_rng(seed)
    n, k = 6, 8
    J = 50.0 * rng.normal(size=(3, n))
    g = rng.normal(size=(k, 3))
    return constraints.filter_qp(
        J, np.array([3.0, 1.0, -2.0]), 1e-3, None, 0.0, np.zeros(n), -2 * np.ones(n), 2 * np.ones(n), 3 * np.ones(n),
        10.0, 0.03, 20.0, tuple(f"b{i}" for i in range(k)), np.full(k, 0.6), g / np.linalg.norm(g, axis=1, keepdims=True),
        50.0 * rng.normal(size=(k, 3, n)), np.full(k, 0.5), 20.0, 5.0, rng.normal(size=(2, n)), np.zeros(2))


def run() -> None:
    qp = filter_sized_qp()
    reference = solve(qp, "clarabel").x
    for solver in sorted(qpsolvers.available_solvers):
        if solver == "quadprog":  # GPL: never a dependency
            continue
        result = solve(qp, solver)
        err = np.nan if not result.ok else float(np.max(np.abs(result.x - reference)))
        t = time_calls_us(lambda i: solve(qp, solver), 300)[20:]
        print(f"  {solver:9s} {summary_us(t)}   max |x - clarabel| {err:.1e} rad/s")
