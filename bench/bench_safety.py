"""Safety-filter QP: solve time per qpsolvers backend on a filter-sized problem
(6 joints, 8 boundary rows, 26 tip-speed rows, 2 RCM rows, joint bounds)."""
from __future__ import annotations

import numpy as np
import qpsolvers

from bench.timing import summary_us, time_calls_us
from safety import constraints
from safety.qp import solve


def filter_sized_blocks(seed: int = 0):
    rng = np.random.default_rng(seed)
    n = 6
    J = 50.0 * rng.normal(size=(3, n))  # mm/rad, Meca500-like lever arms
    blocks = [
        constraints.tracking(J, np.array([3.0, 1.0, -2.0]), 1e-3),
        constraints.joint_limits(np.zeros(n), -2 * np.ones(n), 2 * np.ones(n), 3 * np.ones(n), 10.0, 0.03),
        constraints.tip_speed(J, 20.0),
        constraints.equality("rcm", rng.normal(size=(2, n)), np.zeros(2)),
    ]
    for k in range(8):
        g = rng.normal(size=3)
        blocks.append(constraints.barrier(f"b{k}", 0.6, g / np.linalg.norm(g), 50.0 * rng.normal(size=(3, n)), 0.5, 20.0))
    return blocks, n


def run() -> None:
    blocks, n = filter_sized_blocks()
    reference = solve(blocks, n, "clarabel").x
    for solver in sorted(qpsolvers.available_solvers):
        if solver == "quadprog":  # GPL: never a dependency
            continue
        result = solve(blocks, n, solver)
        err = np.nan if not result.ok else float(np.max(np.abs(result.x - reference)))
        t = time_calls_us(lambda i: solve(blocks, n, solver), 300)[20:]
        print(f"  {solver:9s} {summary_us(t)}   max |x - clarabel| {err:.1e} rad/s")
