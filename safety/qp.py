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
    solved, z = _kkt_solution(H, c, A, b, np.zeros((0, n)), np.zeros(0))
    x = z[:n].copy()
    return (OPTIMAL if solved and _feasible(G, h, lb, ub, x, tol) else NEEDS_SOLVER), x


@njit(cache=True)
def _kkt_solution(H, c, A, b, C, d):
    """(solved, z): z = [x, multipliers of A's rows, of C's rows], x the minimiser of
    1/2 x^T H x + c^T x subject to A x = b and C x = d, from its KKT system (Gaussian
    elimination with partial pivoting; a singular system fails the residual check)."""
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
    return _finite(z) and _solves(K, z, rhs), z


@njit(cache=True)
def _feasible(G, h, lb, ub, x, tol) -> bool:
    """G x <= h and lb <= x <= ub, each to tol relative to its bound."""
    return _most_violated(G, h, lb, ub, x, tol) < 0


@njit(cache=True)
def _most_violated(G, h, lb, ub, x, tol) -> int:
    """The constraint x violates most, by its excess over the bound divided by 1 + |bound|,
    if that is above tol: row i of G (i), the lower bound of x_j (m + j), its upper bound
    (m + n + j); -1 for none."""
    m, n = h.shape[0], x.shape[0]
    worst, k = 0.0, -1
    for i in range(m):
        r = -h[i]
        for j in range(n):
            r += G[i, j] * x[j]
        excess = r / (1.0 + abs(h[i])) - tol
        if excess > worst:
            worst, k = excess, i
    for j in range(n):
        low = (lb[j] - x[j]) / (1.0 + abs(lb[j])) - tol
        high = (x[j] - ub[j]) / (1.0 + abs(ub[j])) - tol
        if low > worst:
            worst, k = low, m + j
        if high > worst:
            worst, k = high, m + n + j
    return k


@njit(cache=True)
def warm_solution(H, c, lb, ub, G, h, A, b, held_rows, held_lower, held_upper, tol, max_changes=0):
    """(certified, x): the QP's solution if an active set reached from the guessed one is
    its own. The guess: the rows of G marked in held_rows (m,) and the bounds in
    held_lower / held_upper (n,) bool. The held constraints, as equalities with A x = b,
    give x and their multipliers; the set is certified when x satisfies every constraint
    (relative tol) with non-negative multipliers on the held ones: the KKT certificate of
    the convex QP (H positive definite: the solution is unique, every solver's to its
    rounding). Otherwise up to `max_changes` single changes follow, each releasing the
    held constraint with the most negative multiplier or, with none negative, holding the
    one x violates most (a step's active set mostly differs from the previous step's by
    one constraint). Dependent held rows, or more held constraints than the equalities
    leave free, end the search uncertified, as does its last change."""
    n, p, m = c.shape[0], b.shape[0], h.shape[0]
    rows, lower, upper = held_rows.copy(), held_lower.copy(), held_upper.copy()
    C = np.zeros((m + 2 * n, n))
    d = np.zeros(m + 2 * n)
    source = np.zeros(m + 2 * n, dtype=np.int64)  # C's row k holds constraint source[k] (_most_violated's index)
    x = np.zeros(n)
    for change in range(max_changes + 1):
        a = 0
        for i in range(m):
            if rows[i]:
                C[a], d[a], source[a] = G[i], h[i], i
                a += 1
        for j in range(n):
            if lower[j]:  # -x_j <= -lb_j
                C[a] = 0.0
                C[a, j], d[a], source[a] = -1.0, -lb[j], m + j
                a += 1
            if upper[j]:
                C[a] = 0.0
                C[a, j], d[a], source[a] = 1.0, ub[j], m + n + j
                a += 1
        if a + p > n or (a == 0 and max_changes == 0):  # none held and no change: the screen's set
            return False, x
        solved, z = _kkt_solution(H, c, A, b, C[:a], d[:a])
        x = z[:n].copy()
        if not solved:
            return False, x
        scale, release = 1.0, -1
        for i in range(p + a):
            scale = max(scale, abs(z[n + i]))
        for i in range(a):
            if z[n + p + i] < -1e-9 * scale and (release < 0 or z[n + p + i] < z[n + p + release]):
                release = i
        k = source[release] if release >= 0 else _most_violated(G, h, lb, ub, x, tol)
        if k < 0:
            return True, x
        if change == max_changes:
            return False, x
        held = release < 0  # hold the violated constraint k, or release the held one
        if k < m:
            rows[k] = held
        elif k < m + n:
            lower[k - m] = held
        else:
            upper[k - m - n] = held
    return False, x


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
