"""The filter's quadratic program: blocks contributed by tasks and constraints, stacked
and solved through qpsolvers. A failure is a value (QPResult.reason), never an exception.

    minimise 1/2 x^T H x + c^T x   subject to   G x <= h,  A x = b,  lb <= x <= ub
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np
import qpsolvers
from scipy import sparse

SPARSE_SOLVERS = {"clarabel", "osqp", "scs", "piqp", "highs"}  # take CSC matrices natively


@dataclass(frozen=True, eq=False)
class Block:
    """One contribution to the QP over x (n,): any of cost (H, c), inequalities (G, h),
    equalities (A, b), bounds (lb, ub). `name` labels its inequality rows for reporting."""

    name: str
    H: np.ndarray | None = None
    c: np.ndarray | None = None
    G: np.ndarray | None = None
    h: np.ndarray | None = None
    A: np.ndarray | None = None
    b: np.ndarray | None = None
    lb: np.ndarray | None = None
    ub: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class QPResult:
    """`x` (n,) or None; `reason` "ok" or why not; `row_names` of the stacked G rows,
    `active` the names of inequality rows at their bound; `solve_us` wall time."""

    x: np.ndarray | None
    reason: str
    row_names: tuple[str, ...]
    active: tuple[str, ...]
    solve_us: float

    @property
    def ok(self) -> bool:
        return self.reason == "ok"


def stack(blocks: list[Block], n: int, as_sparse: bool = False) -> tuple[qpsolvers.Problem, tuple[str, ...]]:
    """The qpsolvers Problem of all blocks (costs added, rows stacked, bounds intersected);
    matrices in CSC form when `as_sparse` (what sparse solvers take without converting)."""
    H = np.zeros((n, n))
    c = np.zeros(n)
    G, h, A, b, names = [], [], [], [], []
    lb, ub = np.full(n, -np.inf), np.full(n, np.inf)
    for blk in blocks:
        if blk.H is not None:
            H += blk.H
        if blk.c is not None:
            c += blk.c
        if blk.G is not None:
            G.append(np.atleast_2d(blk.G))
            h.append(np.atleast_1d(blk.h))
            names += [blk.name] * len(h[-1])
        if blk.A is not None:
            A.append(np.atleast_2d(blk.A))
            b.append(np.atleast_1d(blk.b))
        if blk.lb is not None:
            lb = np.maximum(lb, blk.lb)
        if blk.ub is not None:
            ub = np.minimum(ub, blk.ub)
    Gm = np.vstack(G) if G else None
    Am = np.vstack(A) if A else None
    if not all(np.all(np.isfinite(m)) for m in (H, c, *(G + h + A + b))):
        raise ValueError("non-finite QP data")
    if as_sparse:
        H, Gm, Am = (None if m is None else sparse.csc_matrix(m) for m in (H, Gm, Am))
    problem = qpsolvers.Problem(
        H,
        c,
        Gm,
        np.concatenate(h) if h else None,
        Am,
        np.concatenate(b) if b else None,
        lb if np.isfinite(lb).any() else None,
        ub if np.isfinite(ub).any() else None,
    )
    return problem, tuple(names)


def _equality_optimum(problem: qpsolvers.Problem, tol: float) -> np.ndarray | None:
    """The minimiser of the cost under the equalities alone (its KKT system), when it also
    satisfies every inequality and bound: then it is the QP's solution (convex problem,
    no inequality active). None otherwise, or when H is not dense or the system singular."""
    H, c, A, b = problem.P, problem.q, problem.A, problem.b
    if sparse.issparse(H) or (A is not None and sparse.issparse(A)):
        return None
    n = len(c)
    if A is None:
        K, rhs = H, -c
    else:
        m = len(b)
        K = np.empty((n + m, n + m))
        K[:n, :n], K[:n, n:], K[n:, :n], K[n:, n:] = H, A.T, A, 0.0
        rhs = np.concatenate([-c, b])
    try:
        x = np.linalg.solve(K, rhs)[:n]
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(x)):
        return None
    if problem.G is not None and np.any(problem.G @ x > problem.h + tol * (1.0 + np.abs(problem.h))):
        return None
    if problem.lb is not None and np.any(x < problem.lb - tol * (1.0 + np.abs(problem.lb))):
        return None
    if problem.ub is not None and np.any(x > problem.ub + tol * (1.0 + np.abs(problem.ub))):
        return None
    return x


def solve(blocks: list[Block], n: int, solver: str = "clarabel", active_tol: float = 1e-6) -> QPResult:
    """Stack and solve; any failure (inconsistent bounds, infeasible, solver error, NaN
    in the data or the answer) comes back as a QPResult with x None and the reason.

    When the equality-constrained optimum already satisfies every inequality (nothing
    near its bound: most control steps), it is returned without calling the solver;
    it is the solver's answer up to the solver's tolerance."""
    t0 = time.perf_counter()
    try:
        problem, names = stack(blocks, n, as_sparse=solver in SPARSE_SOLVERS)
    except ValueError as exc:
        return QPResult(None, str(exc), (), (), 1e6 * (time.perf_counter() - t0))
    if problem.lb is not None and problem.ub is not None and np.any(problem.lb > problem.ub):
        return QPResult(None, "infeasible: bounds cross", names, (), 1e6 * (time.perf_counter() - t0))
    x = _equality_optimum(problem, active_tol)
    if x is not None:
        return QPResult(x, "ok", names, (), 1e6 * (time.perf_counter() - t0))
    try:
        with warnings.catch_warnings():  # the reason is reported in the result instead
            warnings.simplefilter("ignore")
            solution = qpsolvers.solve_problem(problem, solver=solver)
    except Exception as exc:  # a solver error must not escape the control loop
        return QPResult(None, f"solver error: {type(exc).__name__}: {exc}", names, (), 1e6 * (time.perf_counter() - t0))
    dt = 1e6 * (time.perf_counter() - t0)
    x = solution.x
    if not solution.found or x is None or not np.all(np.isfinite(x)):
        return QPResult(None, "infeasible or not solved", names, (), dt)
    active = ()
    if problem.G is not None:
        slack = problem.h - problem.G @ x
        active = tuple(sorted({nm for nm, s in zip(names, slack) if s <= active_tol * (1.0 + abs(s))}))
    return QPResult(x, "ok", names, active, dt)
