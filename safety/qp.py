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
from collections.abc import Sequence
from typing import NamedTuple

import daqp
import numpy as np
import qpsolvers
from numba import njit
from scipy import sparse

from models.fit.small_linalg import pivoted_solve

SPARSE_SOLVERS = {"clarabel", "osqp", "scs", "piqp", "highs"}  # take CSC matrices natively
_DAQP_INF = 1e30  # DAQP's "no bound"
_DAQP_EQUALITY = 5  # sense flags: active (1) and immutable (4)

NONFINITE, CROSSED, OPTIMAL, NEEDS_SOLVER = 0, 1, 2, 3


class DenseQP(NamedTuple):
    """The QP over x (n,): H (n, n), c (n,), lb/ub (n,) (+-inf: none), G (m, n), h (m,),
    A (p, n), b (p,); `row_names` (m,) label G's rows for reporting (a tuple, or a sequence
    that names a row when indexed: safety.stack.RowNames)."""

    H: np.ndarray
    c: np.ndarray
    lb: np.ndarray
    ub: np.ndarray
    G: np.ndarray
    h: np.ndarray
    A: np.ndarray
    b: np.ndarray
    row_names: Sequence[str]


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
def _solves(K, z, rhs) -> bool:
    """K z = rhs to rounding: |K z - rhs| <= 1e-9 (|rhs| + |K| |z|) row by row (a zero
    pivot, from a singular K, leaves z far from that or not finite)."""
    for i in range(K.shape[0]):
        r = -rhs[i]
        scale = abs(rhs[i])
        for j in range(K.shape[1]):
            r += K[i, j] * z[j]
            scale += abs(K[i, j] * z[j])
        if not abs(r) <= 1e-9 * scale + 1e-300:
            return False
    return True


@njit(cache=True)
def screen(H, c, lb, ub, G, h, A, b, tol):
    """(code, x): NONFINITE data, CROSSED bounds, OPTIMAL with x the minimiser under
    the equalities that also satisfies every inequality and bound (then it is the convex
    QP's solution), or NEEDS_SOLVER (an inequality would be violated, or the KKT
    system is singular)."""
    n = c.shape[0]
    x = np.zeros(n)
    if not (_finite(H) and _finite(c) and _finite(G) and _finite(h) and _finite(A) and _finite(b)):
        return NONFINITE, x
    for i in range(n):
        if np.isnan(lb[i]) or np.isnan(ub[i]):
            return NONFINITE, x
        if lb[i] > ub[i]:
            return CROSSED, x
    solved, x = _kkt_solution(H, c, A, b, np.zeros((0, n)), np.zeros(0), tol)
    return (OPTIMAL if solved and _feasible(G, h, lb, ub, x, tol) else NEEDS_SOLVER), x


@njit(cache=True)
def _kkt_solution(H, c, A, b, C, d, tol):
    """(solved, x): the minimiser of 1/2 x^T H x + c^T x subject to A x = b and C x = d,
    from its KKT system (Gaussian elimination with partial pivoting; a singular system
    fails the residual check), solved False also when a multiplier of C's rows is
    negative (below -1e-9 of the largest): then C's rows are not all binding."""
    n, p, a = c.shape[0], b.shape[0], d.shape[0]
    N = n + p + a
    K = np.zeros((N, N))
    rhs = np.zeros(N)
    K[:n, :n] = H
    rhs[:n] = -c
    for i in range(p + a):
        row = A[i] if i < p else C[i - p]
        for j in range(n):
            K[n + i, j] = K[j, n + i] = row[j]
        rhs[n + i] = b[i] if i < p else d[i - p]
    z = pivoted_solve(K.copy(), rhs, 1e-300)
    x = z[:n].copy()
    if not (_finite(z) and _solves(K, z, rhs)):
        return False, x
    scale = 1.0
    for i in range(p + a):
        scale = max(scale, abs(z[n + i]))
    for i in range(a):  # dual feasibility of the held inequalities
        if z[n + p + i] < -1e-9 * scale:
            return False, x
    return True, x


@njit(cache=True)
def _feasible(G, h, lb, ub, x, tol) -> bool:
    """G x <= h and lb <= x <= ub, each to tol relative to its bound."""
    n = x.shape[0]
    for i in range(h.shape[0]):
        r = 0.0
        for j in range(n):
            r += G[i, j] * x[j]
        if r > h[i] + tol * (1.0 + abs(h[i])):
            return False
    for i in range(n):
        if x[i] < lb[i] - tol * (1.0 + abs(lb[i])) or x[i] > ub[i] + tol * (1.0 + abs(ub[i])):
            return False
    return True


@njit(cache=True)
def warm_solution(H, c, lb, ub, G, h, A, b, held_rows, held_lower, held_upper, tol):
    """(certified, x): the QP's solution if the guessed active set is its own: the rows
    of G marked in held_rows (m,) and the bounds in held_lower / held_upper (n,) bool,
    held as equalities with A x = b, give an x that satisfies every constraint (relative
    tol) with non-negative multipliers on the held ones. That is the KKT certificate of
    the convex QP (H positive definite: the solution is unique, every solver's to its
    rounding); another active set, or dependent rows, is not certified."""
    n, p = c.shape[0], b.shape[0]
    C = np.zeros((G.shape[0] + 2 * n, n))
    d = np.zeros(G.shape[0] + 2 * n)
    a = 0
    for i in range(G.shape[0]):
        if held_rows[i]:
            C[a], d[a] = G[i], h[i]
            a += 1
    for j in range(n):
        if held_lower[j]:  # -x_j <= -lb_j
            C[a, j], d[a] = -1.0, -lb[j]
            a += 1
        if held_upper[j]:
            C[a, j], d[a] = 1.0, ub[j]
            a += 1
    if a == 0 or a + p > n:
        return False, np.zeros(n)
    solved, x = _kkt_solution(H, c, A, b, C[:a], d[:a], tol)
    return solved and _feasible(G, h, lb, ub, x, tol), x


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
    rows, upper, lower, sense = _daqp_data(qp.lb, qp.ub, qp.G, qp.h, qp.A, qp.b)
    x, _, exitflag, _ = daqp.solve(qp.H, qp.c, rows, upper, lower, sense)
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
    code, x = screen(qp.H, qp.c, qp.lb, qp.ub, qp.G, qp.h, qp.A, qp.b, active_tol)
    if code == NONFINITE:
        return QPResult(None, "non-finite QP data", (), 1e6 * (time.perf_counter() - t0))
    if code == CROSSED:
        return QPResult(None, "infeasible: bounds cross", (), 1e6 * (time.perf_counter() - t0))
    if code == OPTIMAL:
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
    if x is None or not _finite(x):
        return QPResult(None, "infeasible or not solved", (), dt)
    at_bound = rows_at_bound(qp.G, qp.h, x, active_tol)
    return QPResult(x, "ok", tuple(sorted({qp.row_names[i] for i in at_bound})) if len(at_bound) else (), dt)


@njit(cache=True)
def rows_at_bound(G, h, x, tol):
    """Indices of the rows of G x <= h within tol (relative) of their bound."""
    out = np.empty(h.shape[0], dtype=np.int64)
    n = 0
    for i in range(h.shape[0]):
        slack = h[i]
        for j in range(x.shape[0]):
            slack -= G[i, j] * x[j]
        if slack <= tol * (1.0 + abs(slack)):
            out[n] = i
            n += 1
    return out[:n]
