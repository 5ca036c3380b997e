"""Safety-filter QP: solve time per qpsolvers backend on the filter's own QP at a state of
the closed loop (6 joints, tip speed polytope, barrier rows of tip, port and shaft against
the prior and of the lens points, RCM rows, joint bounds), with a command that pushes the
tip into the boundary so that rows are active."""
from __future__ import annotations

import numpy as np
import qpsolvers

from bench.timing import summary_us, time_calls_us
from eval.closed_loop import ClosedLoop, ModelSnapshot
from planning import SurgeryScenario, start_posture
from safety import SafetyFilter
from safety.qp import solve, solve_by_solver


def filter_qp():
    """The filter's DenseQP 0.2 mm inside the prior's boundary, pushing outwards at 15 mm/s."""
    loop = ClosedLoop(SurgeryScenario())
    c = loop.scenario.eye_pose.p_WE
    u = loop.scenario.eye_pose.R_WE @ np.array([0.3, -0.2, -0.93])
    u /= np.linalg.norm(u)
    p = c + (loop.prior.radius - 0.5 - 0.2) * u
    q = start_posture(loop.robot, p, loop.scenario.p_WC)
    snap = ModelSnapshot("prior", None, 0.0, np.nan, 0)
    x = loop.filter.inputs(0.0, q, np.concatenate([15.0 * u, [0.0]]), snap, 0.0)[0]
    return SafetyFilter(loop.config.filter).qp(x)


def run() -> None:
    qp = filter_qp()
    reference = solve(qp, "clarabel").x
    print(f"  the filter's QP: {len(qp.c)} joints, {len(qp.h)} inequality rows, {len(qp.b)} equalities; "
          f"active at the solution: {', '.join(solve(qp, 'daqp').active) or 'none'}")
    for solver in sorted(qpsolvers.available_solvers):
        if solver == "quadprog":  # GPL: never a dependency
            continue
        result = solve(qp, solver)
        err = np.nan if not result.ok else float(np.max(np.abs(result.x - reference)))
        t = time_calls_us(lambda i: solve_by_solver(qp, solver), 300)[20:]
        print(f"  {solver:9s} {summary_us(t)}   max |x - clarabel| {err:.1e} rad/s")
