"""The filter's quadratic program, dense, and its solution. A failure is a value
(QPResult.reason), never an exception.

    minimise 1/2 x^T H x + c^T x   subject to   lb <= x <= ub,  G x <= h,  A x = b

Most control steps have no inequality near its bound; then the minimiser under the
equalities alone (one KKT solve, compiled with the data checks) is the answer and no
solver runs. Otherwise DAQP (dense active set, MIT) is called directly, without the
per-call conversions of qpsolvers; every other backend goes through qpsolvers.
"""
from __future__ import annotations

import time
import warnings
from typing import NamedTuple

import daqp
import numpy as np
import qpsolvers
from numba import njit
from scipy import sparse

SPARSE_SOLVERS = {"clarabel", "osqp", "scs", "piqp", "highs"}  # take CSC matrices natively
_DAQP_INF = 1e30  # DAQP's "no bound"
_DAQP_EQUALITY = 5  # sense flags: active (1) and immutable (4)

_NONFINITE, _CROSSED, _OPTIMAL, _NEEDS_SOLVER = 0, 1, 2, 3


class DenseQP(NamedTuple):
    """The QP over x (n,): H (n, n), c (n,), lb/ub (n,) (+-inf: none), G (m, n), h (m,),
    A (p, n), b (p,); `row_names` (m,) label G's rows for reporting."""

    H: np.ndarray
    c: np.ndarray
    lb: np.ndarray
    ub: np.ndarray
    G: np.ndarray
    h: np.ndarray
    A: np.ndarray
    b: np.ndarray
    row_names: tuple


class QPResult(NamedTuple):
    """`x` (n,) or None; `reason` "ok" or why not; `active` the names of the inequality
    rows at their bound; `solve_us` wall time."""

    x: np.ndarray | None
    reason: str
    active: tuple
    solve_us: float

    @property
    def ok(self) -> bool:
        return self.reason == "ok"


@njit(cache=True)
def _finite(a) -> bool:
    for v in a.ravel():
        if not np.isfinite(v):
            return False
    return True


@njit(cache=True)
def _screen(H, c, lb, ub, G, h, A, b, tol):
    """(code, x): _NONFINITE data, _CROSSED bounds, _OPTIMAL with x the minimiser under
    the equalities that also satisfies every inequality and bound (then it is the convex
    QP's solution), or _NEEDS_SOLVER (an inequality would be violated, or the KKT
    system is singular)."""
    n, p = c.shape[0], b.shape[0]
    x = np.zeros(n)
    if not (_finite(H) and _finite(c) and _finite(G) and _finite(h) and _finite(A) and _finite(b)):
        return _NONFINITE, x
    for i in range(n):
        if np.isnan(lb[i]) or np.isnan(ub[i]):
            return _NONFINITE, x
        if lb[i] > ub[i]:
            return _CROSSED, x
    K = np.zeros((n + p, n + p))
    rhs = np.zeros(n + p)
    K[:n, :n] = H
    K[:n, n:] = A.T
    K[n:, :n] = A
    rhs[:n] = -c
    rhs[n:] = b
    x = np.linalg.solve(K, rhs)[:n]  # raises LinAlgError when K is singular
    if not _finite(x):
        return _NEEDS_SOLVER, x
    r = G @ x
    for i in range(h.shape[0]):
        if r[i] > h[i] + tol * (1.0 + abs(h[i])):
            return _NEEDS_SOLVER, x
    for i in range(n):
        if x[i] < lb[i] - tol * (1.0 + abs(lb[i])) or x[i] > ub[i] + tol * (1.0 + abs(ub[i])):
            return _NEEDS_SOLVER, x
    return _OPTIMAL, x


@njit(cache=True)
def _daqp_data(lb, ub, G, h, A, b):
    """DAQP's form of the QP's constraints: (rows [G; A], upper, lower, sense): the bounds
    first (+-inf as DAQP's 1e30), then G's rows (no lower bound), then A's as equalities."""
    n, m, p = lb.shape[0], h.shape[0], b.shape[0]
    rows = np.empty((m + p, n))
    rows[:m] = G
    rows[m:] = A
    upper = np.empty(n + m + p)
    lower = np.empty(n + m + p)
    sense = np.zeros(n + m + p, dtype=np.intc)
    for i in range(n):
        upper[i] = min(ub[i], _DAQP_INF)
        lower[i] = max(lb[i], -_DAQP_INF)
    for i in range(m):
        upper[n + i] = h[i]
        lower[n + i] = -_DAQP_INF
    for i in range(p):
        upper[n + m + i] = lower[n + m + i] = b[i]
        sense[n + m + i] = _DAQP_EQUALITY
    return rows, upper, lower, sense


def _solve_daqp(qp: DenseQP) -> np.ndarray | None:
    x, _, exitflag, _ = daqp.solve(qp.H, qp.c, *_daqp_data(qp.lb, qp.ub, qp.G, qp.h, qp.A, qp.b))
    return x if exitflag > 0 else None


def _solve_qpsolvers(qp: DenseQP, solver: str) -> np.ndarray | None:
    H, G, A = qp.H, qp.G if len(qp.h) else None, qp.A if len(qp.b) else None
    if solver in SPARSE_SOLVERS:
        H, G, A = (None if m is None else sparse.csc_matrix(m) for m in (H, G, A))
    problem = qpsolvers.Problem(H, qp.c, G, qp.h if len(qp.h) else None, A, qp.b if len(qp.b) else None,
                                qp.lb if np.isfinite(qp.lb).any() else None, qp.ub if np.isfinite(qp.ub).any() else None)
    with warnings.catch_warnings():  # the reason is reported in the result instead
        warnings.simplefilter("ignore")
        solution = qpsolvers.solve_problem(problem, solver=solver)
    return solution.x if solution.found else None


def solve(qp: DenseQP, solver: str = "daqp", active_tol: float = 1e-6) -> QPResult:
    """Solve; any failure (non-finite data, crossed bounds, infeasible, solver error, NaN
    in the answer) comes back as a QPResult with x None and the reason. When no
    inequality is active the equality-constrained optimum is returned without a solver
    (it is every solver's answer up to that solver's tolerance)."""
    t0 = time.perf_counter()
    try:
        code, x = _screen(qp.H, qp.c, qp.lb, qp.ub, qp.G, qp.h, qp.A, qp.b, active_tol)
    except np.linalg.LinAlgError:  # singular KKT system: the solver decides
        code = _NEEDS_SOLVER
    if code == _NONFINITE:
        return QPResult(None, "non-finite QP data", (), 1e6 * (time.perf_counter() - t0))
    if code == _CROSSED:
        return QPResult(None, "infeasible: bounds cross", (), 1e6 * (time.perf_counter() - t0))
    if code == _OPTIMAL:
        return QPResult(x, "ok", (), 1e6 * (time.perf_counter() - t0))
    return solve_by_solver(qp, solver, active_tol, t0)


def solve_by_solver(qp: DenseQP, solver: str = "daqp", active_tol: float = 1e-6, t0: float | None = None) -> QPResult:
    """`solve` without the screen: the solver's answer (for a QP whose screen said it needs
    one); the same failures as values; solve_us counted from t0 (perf_counter s, default now)."""
    t0 = time.perf_counter() if t0 is None else t0
    try:
        x = _solve_daqp(qp) if solver == "daqp" else _solve_qpsolvers(qp, solver)
    except Exception as exc:  # a solver error must not escape the control loop
        return QPResult(None, f"solver error: {type(exc).__name__}: {exc}", (), 1e6 * (time.perf_counter() - t0))
    dt = 1e6 * (time.perf_counter() - t0)
    if x is None or not np.all(np.isfinite(x)):
        return QPResult(None, "infeasible or not solved", (), dt)
    slack = qp.h - qp.G @ x
    at_bound = np.flatnonzero(slack <= active_tol * (1.0 + np.abs(slack)))
    return QPResult(x, "ok", tuple(sorted({qp.row_names[i] for i in at_bound})), dt)
