"""Compiled (numba) ellipsoid fit of a scatter matrix: design rows, the ellipsoid-specific
quadric, its centre, semi-axes and rotation.

The fit works in scaled coordinates (x - p0) / scale (models.fit.ellipsoid_fit); an
update of the adaptive model is a handful of operations on 4x4, 6x6 and 10x10 matrices,
each one compiled call here (NumPy's per-call overhead would dominate the arithmetic at
one update per A-scan, 2 kHz). The batch fits use the same kernels.

The ellipsoid-specific fit (Li & Griffiths 2004, k = 4) minimises v^T S v subject to
v1^T C1 v1 = 1. With the Schur complement S' = S11 - S12 S22^-1 S12^T (symmetric,
positive semi-definite) the problem is the pencil S' v1 = lambda C1 v1. C1 has exactly
one positive eigenvalue, so (Sylvester's law of inertia) the symmetric matrix
K = L^-1 C1 L^-T, with S' = L L^T, has exactly one positive eigenvalue mu = 1 / lambda,
and its eigenvector w gives the solution v1 = L^-T w: a symmetric eigenproblem, real by
construction (a general eigensolver on C1^-1 S' may return near-equal negative
eigenvalues as complex pairs), solved by shifted power iteration (the positive
eigenvalue is the largest), finished by Rayleigh quotient iteration where the power
iteration is slow, with cyclic Jacobi as the fallback. S' is singular when the
points lie exactly on a quadric (noise-free data): its null vector is then the answer
if it is an ellipsoid (v1^T C1 v1 > 0), no answer exists on the k = 4 boundary (= 0: a
paraboloid, a cylinder, semi-axes (a, a, a/2)), and otherwise the minimiser is found as
for noisy data, where a relative 1e-15 on the diagonal of S' keeps the Cholesky factor
defined. Results agree with SciPy's general eigensolver to 1e-7 mm on noisy patches
(tests/models/fit/test_ellipsoid_fit.py).

Status codes of `fit_quadric` and `fit_ellipsoid_scatter`: see FIT_STATUS.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models.fit.small_linalg import cholesky, dot, eigh_sym, lower_inverse, mat_vec, pivoted_solve

FIT_STATUS = ("ok", "too_few_points", "collinear", "coplanar", "not_ellipsoid")
MIN_POINTS = 9
PLANARITY_TOL = 1e-10  # smallest / largest point-cloud variance below which data is flat
_REGULARISATION = 1e-15  # relative to trace(S'), see the module doc
POWER_ITERATIONS = 40  # power steps at the most, before the Jacobi solver
RQI_AFTER = 6  # power steps before Rayleigh quotient iteration may take over (_top_eigenvector)
RQI_STEPS = 6  # Rayleigh quotient steps (cubic convergence: 2-3 suffice) before the Jacobi fallback
NEAR_SINGULAR = 1e-8  # smallest Cholesky pivot^2 / largest diagonal of S' that asks for its eigenvalues
EXACT_QUADRIC = 1e-12  # smallest / largest eigenvalue of S' at which the points lie on one quadric
BOUNDARY = 1e-12  # |v1^T C1 v1| of a unit v1 below which a quadric is on the k = 4 boundary

# v1^T C1 v1 = 4 J - I^2 for v1 = (a, b, c, f, g, h) (k = 4).
C1 = np.zeros((6, 6))
C1[:3, :3] = 1.0
np.fill_diagonal(C1[:3, :3], -1.0)
C1[3:, 3:] = -4.0 * np.eye(3)


@njit(cache=True)
def add_design_rows(S, P, p0, scale):
    """S (10, 10) += sum m m^T over the design rows m of the points P (N, 3) mm, taken in
    the scaled coordinates (p - p0) / scale; in place."""
    add_weighted_design_rows(S, P, p0, scale, np.ones(P.shape[0]))


@njit(cache=True, inline="always")
def design_row(x, y, z, m):
    """The quadric's design row of the scaled point (x, y, z) written to m (10,):
    [x^2, y^2, z^2, 2yz, 2xz, 2xy, 2x, 2y, 2z, 1] (the order of the fits' coefficients v)."""
    m[0], m[1], m[2], m[3], m[4] = x * x, y * y, z * z, 2 * y * z, 2 * x * z
    m[5], m[6], m[7], m[8], m[9] = 2 * x * y, 2 * x, 2 * y, 2 * z, 1.0


@njit(cache=True)
def add_weighted_design_rows(S, P, p0, scale, w):
    """S (10, 10) += sum w_n m_n m_n^T (add_design_rows with a weight w (N,) per point; a
    weight of 1 gives add_design_rows' sums exactly); in place."""
    m = np.empty(10)
    U = np.zeros((10, 10))  # the upper triangle of the sum, mirrored once at the end
    for n in range(P.shape[0]):
        design_row((P[n, 0] - p0[0]) / scale, (P[n, 1] - p0[1]) / scale, (P[n, 2] - p0[2]) / scale, m)
        wn = w[n]
        for i in range(10):
            a = wn * m[i]
            for j in range(i, 10):
                U[i, j] += a * m[j]
    for i in range(10):
        for j in range(i, 10):
            S[i, j] += U[i, j]
            if j != i:
                S[j, i] += U[i, j]


@njit(cache=True)
def _degeneracy(S):
    """Status code (FIT_STATUS) of the cloud behind S: 0 when spread in 3-D."""
    n = S[9, 9]
    if n < MIN_POINTS:
        return 1
    mean = S[6:9, 9] / (2.0 * n)
    cov = S[6:9, 6:9] / (4.0 * n) - np.outer(mean, mean)
    w = eigh_sym(cov)[0]
    if not (w[2] > 0.0) or w[1] <= PLANARITY_TOL * w[2]:
        return 2
    if w[0] <= PLANARITY_TOL * w[2]:
        return 3
    return 0


@njit(cache=True)
def _schur_complement(S, Li22):
    """(X = S22^-1 S12^T (4, 6), S' = S11 - S12 X symmetrised (6, 6)) of the scatter matrix
    S (10, 10), with Li22 = L22^-1 of S22's Cholesky factor: X = Li22^T (Li22 S12^T), by
    loops in one pass each (every sum in index order)."""
    T = np.zeros((4, 6))  # Li22 S12^T
    for i in range(4):
        for l in range(i + 1):  # Li22 is lower triangular
            a = Li22[i, l]
            for j in range(6):
                T[i, j] += a * S[j, 6 + l]
    X = np.zeros((4, 6))
    for i in range(4):
        for l in range(i, 4):  # Li22^T is upper triangular
            a = Li22[l, i]
            for j in range(6):
                X[i, j] += a * T[l, j]
    Sp = np.zeros((6, 6))  # S12 X first, then S11 - S12 X
    for i in range(6):
        for l in range(4):
            a = S[i, 6 + l]
            for j in range(6):
                Sp[i, j] += a * X[l, j]
    for i in range(6):
        for j in range(6):
            Sp[i, j] = S[i, j] - Sp[i, j]
    for i in range(6):
        for j in range(i + 1, 6):
            Sp[i, j] = Sp[j, i] = 0.5 * (Sp[i, j] + Sp[j, i])
    return X, Sp


@njit(cache=True)
def _congruence_C1(Li):
    """K = Li C1 Li^T (6, 6) symmetrised, for the lower-triangular Li: the sums over the
    non-zero terms of Li and C1 only (C1: the 3x3 block of -1 / +1 and -4 I), in index order."""
    M = np.zeros((6, 6))  # Li C1
    for i in range(6):
        for l in range(min(i, 2) + 1):
            a = Li[i, l]
            for j in range(3):
                M[i, j] += a * C1[l, j]
        for j in range(3, i + 1):
            M[i, j] = Li[i, j] * -4.0
    K = np.zeros((6, 6))  # M Li^T
    for i in range(6):
        for j in range(6):
            s = 0.0
            for l in range(j + 1):
                s += M[i, l] * Li[j, l]
            K[i, j] = s
    for i in range(6):
        for j in range(i + 1, 6):
            K[i, j] = K[j, i] = 0.5 * (K[i, j] + K[j, i])
    return K


@njit(cache=True)
def fit_quadric(S, check_spread):
    """(status code, v (10,)): the ellipsoid-specific least-squares quadric of scatter
    matrix S; `check_spread` adds the collinear/coplanar test (too few points are always
    refused). v holds zeros unless the code is 0."""
    v = np.zeros(10)
    code = _degeneracy(S) if check_spread else (1 if S[9, 9] < MIN_POINTS else 0)
    if code:
        return code, v
    L22, ok = cholesky(np.ascontiguousarray(S[6:, 6:]))
    if not ok:  # S22 is positive definite unless the data is flat
        return 3, v
    Li22 = lower_inverse(L22)
    X, Sp = _schur_complement(S, Li22)
    L, ok = cholesky(Sp)
    pivot2 = np.inf
    for i in range(6):
        pivot2 = min(pivot2, L[i, i] ** 2)
    if not ok or pivot2 <= NEAR_SINGULAR * np.max(np.diag(Sp)):  # maybe points on one quadric: look closer
        lam, Q = eigh_sym(Sp)
        if lam[0] <= EXACT_QUADRIC * lam[5]:  # a quadric through every point (noise-free data)
            v1 = np.ascontiguousarray(Q[:, 0])
            c = dot(v1, mat_vec(C1, v1))
            if c > BOUNDARY:  # an ellipsoid: the exact answer
                return _with_linear_part(v1 / np.sqrt(c), X)
            if c >= -BOUNDARY:  # on the k = 4 boundary 4J - I^2 = 0: v^T S v -> 0 only as v -> infinity
                return 4, v
            # else the exact quadric is no ellipsoid: the constrained minimiser lies elsewhere
        L, ok = cholesky(Sp + _REGULARISATION * np.trace(Sp) * np.eye(6))
        if not ok:
            return 4, v
    Li = lower_inverse(L)
    start = mat_vec(L.T, np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0]))  # the sphere direction (v1^T C1 v1 > 0)
    w, mu = _top_eigenvector(_congruence_C1(Li), start)
    if not (mu > 0.0):
        return 4, v
    v1 = mat_vec(Li.T, w)
    c = dot(v1, mat_vec(C1, v1))
    if not (c > BOUNDARY * dot(v1, v1)):
        return 4, v
    return _with_linear_part(v1 / np.sqrt(c), X)


@njit(cache=True)
def _top_eigenvector(K, start):
    """(unit eigenvector, eigenvalue) of the largest eigenvalue of the symmetric K (n, n),
    which has exactly one positive eigenvalue mu (see the module doc): power iteration
    on K + sigma I, sigma from Gershgorin's bound so that every eigenvalue of the shifted
    matrix is >= 0 and the largest dominates; from `start` (not orthogonal to the
    answer), until the residual |K y - mu y| is at rounding level of mu. For data near an
    ellipsoid mu stands far above the rest: a few tens of 6x6 products. On small early
    patches it does not, and the power iteration crawls; once it has taken RQI_AFTER
    steps and its residual is below mu / 2, an eigenvalue lies within that of mu and
    every other one is negative, more than mu away, so Rayleigh quotient iteration
    converges to the answer: two or three 6x6 solves. eigh_sym when neither converges."""
    n = K.shape[0]
    g = np.inf
    norm_K = 0.0  # largest absolute row sum: a bound on |K|, the scale of rounding in K y
    for i in range(n):
        row = 0.0
        for j in range(n):
            row += abs(K[i, j])
        g = min(g, K[i, i] - (row - abs(K[i, i])))
        norm_K = max(norm_K, row)
    sigma = max(0.0, -g)
    y = start / np.sqrt(dot(start, start))
    Ky = np.empty(n)
    for step in range(POWER_ITERATIONS):  # in place: a 6x6 product per step, no temporary arrays
        for i in range(n):
            s = 0.0
            for j in range(n):
                s += K[i, j] * y[j]
            Ky[i] = s
        mu = dot(y, Ky)
        r2 = 0.0
        for i in range(n):
            r = Ky[i] - mu * y[i]
            r2 += r * r
        if r2 <= 1e-28 * mu * mu:  # residual |K y - mu y| <= 1e-14 |mu|: converged, whatever the ratio
            return y, mu
        if step >= RQI_AFTER and mu > 0.0 and r2 < 0.25 * mu * mu:
            return _rayleigh_quotient_iteration(K, y, mu, norm_K)
        for i in range(n):
            y[i] = Ky[i] + sigma * y[i]
        norm = np.sqrt(dot(y, y))
        for i in range(n):
            y[i] /= norm
    lam, W = eigh_sym(K)
    return np.ascontiguousarray(W[:, n - 1]), lam[n - 1]


@njit(cache=True)
def _rayleigh_quotient_iteration(K, y, mu, norm_K):
    """(unit eigenvector, eigenvalue) of the symmetric K (n, n) nearest to mu, from y
    (unit) with Rayleigh quotient mu, by Rayleigh quotient iteration until the residual
    is at rounding level of K (|K| <= norm_K); eigh_sym's largest eigenpair when not
    converged in RQI_STEPS (the caller asks for the largest, which is the nearest)."""
    n = K.shape[0]
    A = np.empty((n, n))
    for _ in range(RQI_STEPS):
        for i in range(n):
            for j in range(n):
                A[i, j] = K[i, j] - (mu if i == j else 0.0)
        y = pivoted_solve(A, y, 1e-300 + 1e-16 * norm_K)
        y /= np.sqrt(dot(y, y))
        Ky = mat_vec(K, y)
        mu = dot(y, Ky)
        r2 = 0.0
        for i in range(n):
            r = Ky[i] - mu * y[i]
            r2 += r * r
        if r2 <= 1e-28 * max(mu * mu, norm_K * norm_K):
            return y, mu
    lam, W = eigh_sym(K)
    return np.ascontiguousarray(W[:, n - 1]), lam[n - 1]


@njit(cache=True)
def _with_linear_part(v1, X):
    """(0, v (10,)): the quadratic part v1 (6,) with its optimal linear part v2 = -S22^-1 S12^T v1."""
    v = np.empty(10)
    v[:6] = v1
    v[6:] = -mat_vec(X, v1)
    return 0, v


@njit(cache=True)
def quadric_parameters(v, p0, scale):
    """(ok, centre (3,), semi-axes (3,) descending, rotation (3, 3) with the axes as
    columns, right-handed) in mm and the frame of p0, of the quadric v (10,) given in
    coordinates (x - p0) / scale; not ok when it is not a real ellipsoid."""
    a, b, c, f, g, h = v[0], v[1], v[2], v[3], v[4], v[5]
    A = np.empty((3, 3))
    A[0, 0], A[0, 1], A[0, 2], A[1, 0], A[1, 1], A[1, 2], A[2, 0], A[2, 1], A[2, 2] = a, h, g, h, b, f, g, f, c
    center = np.zeros(3)
    radii = np.zeros(3)
    R = np.eye(3)
    detA = a * (b * c - f * f) - h * (h * c - f * g) + g * (h * f - b * g)
    if not (abs(detA) > 1e-300):
        return False, center, radii, R
    # A symmetric: A^-1 = adj / det; the centre w = -A^-1 v[6:9]
    adj = np.empty((3, 3))
    adj[0, 0], adj[0, 1], adj[0, 2] = b * c - f * f, g * f - h * c, h * f - b * g
    adj[1, 0], adj[1, 1], adj[1, 2] = g * f - h * c, a * c - g * g, h * g - a * f
    adj[2, 0], adj[2, 1], adj[2, 2] = h * f - b * g, h * g - a * f, a * b - h * h
    w = np.empty(3)
    for i in range(3):
        w[i] = -(adj[i, 0] * v[6] + adj[i, 1] * v[7] + adj[i, 2] * v[8]) / detA
    wAw = 0.0
    for i in range(3):
        wAw += w[i] * (A[i, 0] * w[0] + A[i, 1] * w[1] + A[i, 2] * w[2])
    mu = wAw - v[9]
    for i in range(3):
        for j in range(3):
            A[i, j] /= mu
    lam, E = eigh_sym(A)
    if not (lam[0] > 0.0 and np.isfinite(lam[2])):
        return False, center, radii, R
    E = np.ascontiguousarray(E)
    det = (E[0, 0] * (E[1, 1] * E[2, 2] - E[1, 2] * E[2, 1]) - E[0, 1] * (E[1, 0] * E[2, 2] - E[1, 2] * E[2, 0])
           + E[0, 2] * (E[1, 0] * E[2, 1] - E[1, 1] * E[2, 0]))
    if det < 0.0:  # eigenvectors come with arbitrary signs: make the frame right-handed
        E[:, 2] = -E[:, 2]
    return True, p0 + scale * w, scale / np.sqrt(lam), E


@njit(cache=True)
def fit_ellipsoid_scatter(S, p0, scale, check_spread):
    """(status code, v (10,), centre (3,), semi-axes (3,), rotation (3, 3)): fit_quadric
    and quadric_parameters in one call (code 4 when the best quadric is no real ellipsoid)."""
    code, v = fit_quadric(S, check_spread)
    ok = code == 0
    center, radii, R = np.zeros(3), np.zeros(3), np.eye(3)
    if ok:
        ok, center, radii, R = quadric_parameters(v, p0, scale)
        if not ok:
            code = 4
    return code, v, center, radii, R


@njit(cache=True)
def spread_check_due(checked_at, n, recheck):
    """Whether the fit of n points runs the collinear/coplanar test, the last passed one
    at `checked_at` points (0: none): adding points only widens a cloud's scatter about
    its mean, so once spread in 3-D it stays so; the test is still repeated every
    `recheck` points (models.fit.ellipsoid_fit.IncrementalEllipsoidFit)."""
    return checked_at == 0 or n - checked_at >= recheck

