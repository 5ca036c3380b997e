"""Compiled (numba) kernels of the per-A-scan model update: small fixed-size linear algebra.

An update of the adaptive model is a handful of operations on 4x4, 6x6 and 10x10
matrices; in NumPy each costs one to three microseconds of call overhead, which at one
update per A-scan (2 kHz) dominates the arithmetic. These kernels do the same
arithmetic in one compiled call each. They are the only implementation (the batch fits
use them too) and work in the fits' scaled coordinates (models.ellipsoid_fit); an
update's whole work (gate, sphere filter, scatter matrix, scan range, refit,
residuals), by one A-scan or by a packet, is one call of `packet_update`, which runs
the same kernels as the general update path.

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
(tests/models/test_ellipsoid_fit.py).

Status codes of `fit_quadric` and `fit_ellipsoid_scatter`: see FIT_STATUS.
"""
from __future__ import annotations

import numpy as np
from numba import njit

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
def _mv(A, x):
    """A @ x by loops: for these few-by-few matrices a BLAS call's overhead exceeds the work."""
    y = np.zeros(A.shape[0])
    for i in range(A.shape[0]):
        s = 0.0
        for j in range(A.shape[1]):
            s += A[i, j] * x[j]
        y[i] = s
    return y


@njit(cache=True)
def _dot(a, b):
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * b[i]
    return s


@njit(cache=True)
def add_design_rows(S, P, p0, scale):
    """S (10, 10) += sum m m^T over the design rows m of the points P (N, 3) mm, taken in
    the scaled coordinates (p - p0) / scale; in place."""
    add_weighted_design_rows(S, P, p0, scale, np.ones(P.shape[0]))


@njit(cache=True)
def add_weighted_design_rows(S, P, p0, scale, w):
    """S (10, 10) += sum w_n m_n m_n^T (add_design_rows with a weight w (N,) per point; a
    weight of 1 gives add_design_rows' sums exactly); in place."""
    m = np.empty(10)
    U = np.zeros((10, 10))  # the upper triangle of the sum, mirrored once at the end
    for n in range(P.shape[0]):
        x, y, z = (P[n, 0] - p0[0]) / scale, (P[n, 1] - p0[1]) / scale, (P[n, 2] - p0[2]) / scale
        m[0], m[1], m[2], m[3], m[4] = x * x, y * y, z * z, 2 * y * z, 2 * x * z
        m[5], m[6], m[7], m[8], m[9] = 2 * x * y, 2 * x, 2 * y, 2 * z, 1.0
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
def add_sphere_rows(Y, y, P, p0, scale):
    """The sphere filter's information form, in place: Y (4, 4) += sum h h^T, y (4,) +=
    sum h |x|^2 over the points P (N, 3) mm in scaled coordinates x = (p - p0) / scale,
    h = [2x, 2y, 2z, 1]."""
    for n in range(P.shape[0]):
        x0, x1, x2 = (P[n, 0] - p0[0]) / scale, (P[n, 1] - p0[1]) / scale, (P[n, 2] - p0[2]) / scale
        h = np.array([2.0 * x0, 2.0 * x1, 2.0 * x2, 1.0])
        r2 = x0 * x0 + x1 * x1 + x2 * x2
        for i in range(4):
            y[i] += h[i] * r2
            for j in range(4):
                Y[i, j] += h[i] * h[j]


@njit(cache=True)
def _cholesky(A):
    """(L, ok): the lower Cholesky factor of the symmetric A (n, n); not ok when A is not
    positive definite (an answer, not an exception: a singular matrix is degenerate data)."""
    n = A.shape[0]
    L = np.zeros((n, n))
    for j in range(n):
        acc = 0.0  # the sums run in index order, from 0: no temporary arrays
        for k in range(j):
            acc += L[j, k] * L[j, k]
        s = A[j, j] - acc
        if not s > 1e-300:
            return L, False
        L[j, j] = np.sqrt(s)
        for i in range(j + 1, n):
            acc = 0.0
            for k in range(j):
                acc += L[i, k] * L[j, k]
            L[i, j] = (A[i, j] - acc) / L[j, j]
    return L, True


@njit(cache=True)
def sphere_state(Y, y):
    """(state [cx, cy, cz, r^2 - |c|^2] (4,), ok): the least-squares solution Y^-1 y; not ok
    when Y is not positive definite (coplanar points) or the radius is not real."""
    L, ok = _cholesky(Y)
    x = np.zeros(4)
    if not ok:
        return x, False
    u = np.zeros(4)
    for i in range(4):
        acc = 0.0
        for k in range(i):
            acc += L[i, k] * u[k]
        u[i] = (y[i] - acc) / L[i, i]
    for i in range(3, -1, -1):
        acc = 0.0
        for k in range(i + 1, 4):
            acc += L[k, i] * x[k]
        x[i] = (u[i] - acc) / L[i, i]
    return x, x[3] + x[0] * x[0] + x[1] * x[1] + x[2] * x[2] > 0.0


@njit(cache=True)
def eigh_sym(A):
    """(eigenvalues ascending (n,), eigenvectors as columns (n, n)) of the symmetric A, by
    cyclic Jacobi rotations (Golub & Van Loan 8.5): for the 3x3-6x6 matrices here a few
    microseconds, against tens for a LAPACK call through NumPy, and accurate to rounding."""
    n = A.shape[0]
    a = A.copy()
    V = np.eye(n)
    scale = 0.0
    for i in range(n):
        for j in range(n):
            scale += a[i, j] * a[i, j]
    for _ in range(50):
        off = 0.0
        for i in range(n):
            for j in range(i + 1, n):
                off += a[i, j] * a[i, j]
        if off <= 1e-32 * scale:
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = a[p, q]
                if apq == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                t = (1.0 if theta >= 0.0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
                c = 1.0 / np.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):  # a <- a J (columns p, q)
                    akp, akq = a[k, p], a[k, q]
                    a[k, p] = c * akp - s * akq
                    a[k, q] = s * akp + c * akq
                for k in range(n):  # a <- J^T a (rows p, q)
                    apk, aqk = a[p, k], a[q, k]
                    a[p, k] = c * apk - s * aqk
                    a[q, k] = s * apk + c * aqk
                for k in range(n):
                    vkp, vkq = V[k, p], V[k, q]
                    V[k, p] = c * vkp - s * vkq
                    V[k, q] = s * vkp + c * vkq
    w = np.empty(n)
    for i in range(n):
        w[i] = a[i, i]
    order = np.argsort(w)
    return w[order], np.ascontiguousarray(V[:, order])


@njit(cache=True)
def _lower_inverse(L):
    """L^-1 of the lower-triangular L (n, n) with a positive diagonal, by forward substitution."""
    n = L.shape[0]
    X = np.zeros((n, n))
    for j in range(n):
        X[j, j] = 1.0 / L[j, j]
        for i in range(j + 1, n):
            s = 0.0
            for k in range(j, i):
                s += L[i, k] * X[k, j]
            X[i, j] = -s / L[i, i]
    return X


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
    L22, ok = _cholesky(np.ascontiguousarray(S[6:, 6:]))
    if not ok:  # S22 is positive definite unless the data is flat
        return 3, v
    Li22 = _lower_inverse(L22)
    X, Sp = _schur_complement(S, Li22)
    L, ok = _cholesky(Sp)
    pivot2 = np.inf
    for i in range(6):
        pivot2 = min(pivot2, L[i, i] ** 2)
    if not ok or pivot2 <= NEAR_SINGULAR * np.max(np.diag(Sp)):  # maybe points on one quadric: look closer
        lam, Q = eigh_sym(Sp)
        if lam[0] <= EXACT_QUADRIC * lam[5]:  # a quadric through every point (noise-free data)
            v1 = np.ascontiguousarray(Q[:, 0])
            c = _dot(v1, _mv(C1, v1))
            if c > BOUNDARY:  # an ellipsoid: the exact answer
                return _with_linear_part(v1 / np.sqrt(c), X)
            if c >= -BOUNDARY:  # on the k = 4 boundary 4J - I^2 = 0: v^T S v -> 0 only as v -> infinity
                return 4, v
            # else the exact quadric is no ellipsoid: the constrained minimiser lies elsewhere
        L, ok = _cholesky(Sp + _REGULARISATION * np.trace(Sp) * np.eye(6))
        if not ok:
            return 4, v
    Li = _lower_inverse(L)
    start = _mv(L.T, np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0]))  # the sphere direction (v1^T C1 v1 > 0)
    w, mu = _top_eigenvector(_congruence_C1(Li), start)
    if not (mu > 0.0):
        return 4, v
    v1 = _mv(Li.T, w)
    c = _dot(v1, _mv(C1, v1))
    if not (c > BOUNDARY * _dot(v1, v1)):
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
    y = start / np.sqrt(_dot(start, start))
    Ky = np.empty(n)
    for step in range(POWER_ITERATIONS):  # in place: a 6x6 product per step, no temporary arrays
        for i in range(n):
            s = 0.0
            for j in range(n):
                s += K[i, j] * y[j]
            Ky[i] = s
        mu = _dot(y, Ky)
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
        norm = np.sqrt(_dot(y, y))
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
        y /= np.sqrt(_dot(y, y))
        Ky = _mv(K, y)
        mu = _dot(y, Ky)
        r2 = 0.0
        for i in range(n):
            r = Ky[i] - mu * y[i]
            r2 += r * r
        if r2 <= 1e-28 * max(mu * mu, norm_K * norm_K):
            return y, mu
    lam, W = eigh_sym(K)
    return np.ascontiguousarray(W[:, n - 1]), lam[n - 1]


@njit(cache=True)
def pivoted_solve(A, b, tiny):
    """x with A x = b for A (n, n) (overwritten), by Gaussian elimination with partial
    pivoting; a pivot below `tiny` is replaced by `tiny` (for a shift at an eigenvalue,
    where the near-singular solve is the point: its answer is the eigenvector)."""
    n = A.shape[0]
    x = b.copy()
    for k in range(n):
        p = k
        for i in range(k + 1, n):
            if abs(A[i, k]) > abs(A[p, k]):
                p = i
        if p != k:
            for j in range(n):
                A[k, j], A[p, j] = A[p, j], A[k, j]
            x[k], x[p] = x[p], x[k]
        if abs(A[k, k]) < tiny:
            A[k, k] = tiny
        for i in range(k + 1, n):
            f = A[i, k] / A[k, k]
            for j in range(k + 1, n):
                A[i, j] -= f * A[k, j]
            x[i] -= f * x[k]
    for i in range(n - 1, -1, -1):
        s = x[i]
        for j in range(i + 1, n):
            s -= A[i, j] * x[j]
        x[i] = s / A[i, i]
    return x


@njit(cache=True)
def _with_linear_part(v1, X):
    """(0, v (10,)): the quadratic part v1 (6,) with its optimal linear part v2 = -S22^-1 S12^T v1."""
    v = np.empty(10)
    v[:6] = v1
    v[6:] = -_mv(X, v1)
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


# dQ/dx = 2(a x + h y + g z + p), dQ/dy = 2(h x + b y + f z + q), dQ/dz = 2(g x + f y + c z + r):
# row i lists the coefficients of v multiplying [x, y, z, 1] in component i.
GRAD_ROWS = np.array([[0, 5, 4, 6], [5, 1, 3, 7], [4, 3, 2, 8]])


@njit(cache=True)
def taubin_residuals(S, V):
    """(k,) RMS point-to-surface distance (scaled units) of each quadric row of V (k, 10)
    over the points of S, in Taubin's first-order form sqrt(v^T S v / sum |grad Q|^2),
    from the moments alone (S[6:, 6:] holds the moments of [2x, 2y, 2z, 1])."""
    M = np.empty((4, 4))
    for i in range(4):
        for j in range(4):
            M[i, j] = S[6 + i, 6 + j] * (0.5 if i < 3 else 1.0) * (0.5 if j < 3 else 1.0)
    out = np.empty(V.shape[0])
    for k in range(V.shape[0]):  # the products by loops, in index order: no temporary arrays
        q2 = 0.0
        for i in range(10):
            Sv = 0.0
            for j in range(10):
                Sv += S[i, j] * V[k, j]
            q2 += V[k, i] * Sv
        g2 = 0.0
        for i in range(3):
            wMw = 0.0
            for a in range(4):
                Mw = 0.0
                for b in range(4):
                    Mw += M[a, b] * V[k, GRAD_ROWS[i, b]]
                wMw += V[k, GRAD_ROWS[i, a]] * Mw
            g2 += wMw
        g2 *= 4.0
        out[k] = np.sqrt(max(q2, 0.0) / g2) if g2 > 0.0 else np.inf
    return out


SCAN_BLOCK = 16  # points per bounding ball of models.scan_range (16: ~1 us per point on the paper spiral, 64: ~2.5)


@njit(cache=True)
def diameter_after_adding(X, block_r, n, P, p0, diameter):
    """The diameter (mm) of the first n rows of X (cap, 3) and the rows x = p - p0 of the
    points P (k, 3) mm, given theirs (`diameter`); the x are stored as rows n.. n + k - 1
    and their blocks updated, in place. Block b holds rows [b B, (b + 1) B) with B =
    SCAN_BLOCK, its ball centred on row b B with radius block_r[b]. A block is skipped for
    the whole batch when the new points' ball (about the first, radius rho) cannot reach
    past the largest distance so far: |x_0 - centre| + rho + radius <= `diameter`; the
    others are skipped per point as |x - centre| + radius <= the largest distance found
    so far. The new points are compared with each other directly."""
    k = P.shape[0]
    for i in range(k):
        X[n + i, 0], X[n + i, 1], X[n + i, 2] = P[i, 0] - p0[0], P[i, 1] - p0[1], P[i, 2] - p0[2]
    m0, m1, m2 = X[n, 0], X[n, 1], X[n, 2]
    rho = 0.0
    for i in range(1, k):
        rho = max(rho, np.sqrt((X[n + i, 0] - m0) ** 2 + (X[n + i, 1] - m1) ** 2 + (X[n + i, 2] - m2) ** 2))
    n_blocks = (n + SCAN_BLOCK - 1) // SCAN_BLOCK
    batch = k > 1  # one point (an A-scan): its per-point test below is this one, no pre-pass
    candidates = np.empty(n_blocks if batch else 0, np.int64)
    n_cand = 0 if batch else n_blocks
    for b in range(n_blocks if batch else 0):
        c = b * SCAN_BLOCK
        slack = diameter - block_r[b] - rho
        if not (slack >= 0.0 and (m0 - X[c, 0]) ** 2 + (m1 - X[c, 1]) ** 2 + (m2 - X[c, 2]) ** 2 <= slack * slack):
            candidates[n_cand] = b
            n_cand += 1
    best, best2 = diameter, diameter * diameter
    for i in range(k):
        x0, x1, x2 = X[n + i, 0], X[n + i, 1], X[n + i, 2]
        for q in range(n_cand):
            b = candidates[q] if batch else q
            c = b * SCAN_BLOCK
            slack = best - block_r[b]  # |x - centre| + radius <= best, without a square root
            if slack >= 0.0 and (x0 - X[c, 0]) ** 2 + (x1 - X[c, 1]) ** 2 + (x2 - X[c, 2]) ** 2 <= slack * slack:
                continue
            for j in range(c, min(n, c + SCAN_BLOCK)):
                d2 = (x0 - X[j, 0]) ** 2 + (x1 - X[j, 1]) ** 2 + (x2 - X[j, 2]) ** 2
                if d2 > best2:
                    best2 = d2
        for j in range(n, n + i):
            d2 = (x0 - X[j, 0]) ** 2 + (x1 - X[j, 1]) ** 2 + (x2 - X[j, 2]) ** 2
            if d2 > best2:
                best2 = d2
        best = np.sqrt(best2)
    for j in range(n, n + k):
        b = j // SCAN_BLOCK
        if j % SCAN_BLOCK == 0:
            block_r[b] = 0.0
        else:
            c = b * SCAN_BLOCK
            r = np.sqrt((X[j, 0] - X[c, 0]) ** 2 + (X[j, 1] - X[c, 1]) ** 2 + (X[j, 2] - X[c, 2]) ** 2)
            if r > block_r[b]:
                block_r[b] = r
    return np.sqrt(best2)


@njit(cache=True)
def sphere_absorb(Y, y, P, p0, scale, n_total):
    """add_sphere_rows, then (state (4,), ok) of sphere_state once the filter holds
    n_total >= 4 points (not ok before: fewer than four points define no sphere)."""
    add_sphere_rows(Y, y, P, p0, scale)
    if n_total < 4:
        return np.zeros(4), False
    return sphere_state(Y, y)


@njit(cache=True)
def sphere_center_radius(state, p0, scale, center):
    """Radius (mm) of the sphere filter's state [c, r^2 - |c|^2] (coordinates (x - p0) /
    scale); its centre (mm, frame of p0) is written to center (3,)."""
    cx, cy, cz, k = state[0], state[1], state[2], state[3]
    center[0], center[1], center[2] = p0[0] + scale * cx, p0[1] + scale * cy, p0[2] + scale * cz
    return scale * np.sqrt(k + cx * cx + cy * cy + cz * cz)


@njit(cache=True)
def sampson_one(v, x, y, z):
    """|Q| / |grad Q| of the point (x, y, z) (scaled coordinates) from the quadric v (10,):
    Sampson's first-order distance (scaled units; inf where the gradient vanishes)."""
    a, b, c, f, g, h, p, q, r, d = v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], v[8], v[9]
    Q = a * x * x + b * y * y + c * z * z + 2.0 * (f * y * z + g * x * z + h * x * y + p * x + q * y + r * z) + d
    gx, gy, gz = a * x + h * y + g * z + p, h * x + b * y + f * z + q, g * x + f * y + c * z + r
    grad = 2.0 * np.sqrt(gx * gx + gy * gy + gz * gz)
    return abs(Q) / grad if grad > 0.0 else np.inf


@njit(cache=True)
def sampson_distances(v, X):
    """(K,) sampson_one of each row of X (K, 3) (scaled coordinates) from the quadric v (10,)."""
    out = np.empty(X.shape[0])
    for k in range(X.shape[0]):
        out[k] = sampson_one(v, X[k, 0], X[k, 1], X[k, 2])
    return out


RESIDUAL_REFRESH = 16  # accepted points between refreshes of the gate's robust residual and jump limit (medians)
# models.outlier_gate.GateState's state, in arrays the gate kernel updates in place:
# GATE_PARAMS indexes its float parameters, GATE_COUNTS its integer counters
G_K_RESIDUAL, G_MIN_GATE_MM, G_MIN_POINTS, G_MAX_CONSECUTIVE, G_MAX_JUMP_MM = range(5)
G_REFERENCE, G_RUN, G_N_RECENT, G_REFRESH_AT, G_N_REJECTED = range(5)
# counts[G_REFERENCE]: what the gate's `last` holds: nothing yet, the first point (not yet
# kept: pending until the next one confirms it), or the last point kept
REF_NONE, REF_PENDING, REF_KEPT = range(3)


@njit(cache=True)
def _model_distance(quadric, has_quadric, p0, scale, px, py, pz):
    """Sampson distance (mm) of the point (px, py, pz) mm from the quadric about p0 (0 without one)."""
    if not has_quadric:
        return 0.0
    return scale * sampson_one(quadric, (px - p0[0]) / scale, (py - p0[1]) / scale, (pz - p0[2]) / scale)


@njit(cache=True)
def _remember(counts, last, recent, px, py, pz, d, step):
    """Record a kept point (px, py, pz) mm at distance d mm from the model, `step` mm from
    the point kept before it, as the gate's reference."""
    last[0], last[1], last[2] = px, py, pz
    k = counts[G_N_RECENT] % recent.shape[1]
    recent[0, k], recent[1, k] = d, step
    counts[G_N_RECENT] += 1


@njit(cache=True)
def _refresh_scales(params, counts, scales, recent):
    """The robust residual (1.4826 x the median distance to the model, mm; inf before any
    point) and the jump limit (k_residual x the median step between consecutive kept
    points, within [min_gate_mm, max_jump_mm]; max_jump_mm before any point) of the last
    kept points `recent`, into scales (2,)."""
    m = min(counts[G_N_RECENT], recent.shape[1])
    if m == 0:
        scales[0], scales[1] = np.inf, params[G_MAX_JUMP_MM]
        return
    scales[0] = 1.4826 * np.median(recent[0, :m])
    scales[1] = min(params[G_MAX_JUMP_MM], max(params[G_MIN_GATE_MM], params[G_K_RESIDUAL] * np.median(recent[1, :m])))


@njit(cache=True)
def gate_points(P, keep, quadric, has_quadric, p0, scale, n_model_points, params, counts, last, scales, recent):
    """The innovation gate (models.outlier_gate.OutlierGate) over the points P (N, 3) mm in
    A-scan order; sets keep[:N] and returns (the count of P's rows kept, whether the
    pending first point (in `last` at the call) was confirmed and is kept too, before
    P's rows), updating the gate's state in place: `counts` (GATE_COUNTS: int64), `last`
    (3,) the reference point (mm, see REF_*), `scales` (2,) the robust residual and the
    jump limit (mm, refreshed every RESIDUAL_REFRESH accepted points by _refresh_scales
    from `recent` (2, window): the distances to the model and the steps of the last
    accepted points, mm).
    `quadric` (10,) is the current model about p0 in coordinates (x - p0) / scale
    (ignored unless `has_quadric`: every distance is then 0). The very first point has
    nothing to be compared with: it is held as pending and kept only if the next point
    lies within the jump limit of it (else it is rejected and the next point is pending
    in its place), so that a floater on the first A-scan never becomes the reference
    that turns the retina away. Each later point's jump is measured from the last point
    kept before it, so a rejected floater never becomes the reference for the next
    A-scan; while more than max_consecutive far points have come in a row, they are
    kept: that is retina, not a floater."""
    if counts[G_N_RECENT] >= counts[G_REFRESH_AT]:  # the medians are refreshed every REFRESH points, not per point
        _refresh_scales(params, counts, scales, recent)
        counts[G_REFRESH_AT] = counts[G_N_RECENT] + RESIDUAL_REFRESH
    use_model = n_model_points >= params[G_MIN_POINTS] and scales[0] < np.inf
    gate = max(params[G_MIN_GATE_MM], params[G_K_RESIDUAL] * scales[0]) if use_model else np.inf
    max_jump = scales[1]
    n_kept = 0
    took_pending = False
    pending_at = -1  # the row of P held as pending, -1: the pending point came with an earlier call
    for n in range(P.shape[0]):
        px, py, pz = P[n, 0], P[n, 1], P[n, 2]
        jump = np.sqrt((px - last[0]) ** 2 + (py - last[1]) ** 2 + (pz - last[2]) ** 2)
        d = _model_distance(quadric, has_quadric, p0, scale, px, py, pz)
        if counts[G_REFERENCE] != REF_KEPT:  # no point kept yet: only a confirmed pair gets in
            keep[n] = counts[G_REFERENCE] == REF_PENDING and jump <= max_jump
            if not keep[n]:
                counts[G_N_REJECTED] += counts[G_REFERENCE] == REF_PENDING  # the previous first point: unconfirmed
                last[0], last[1], last[2] = px, py, pz
                counts[G_REFERENCE] = REF_PENDING
                pending_at = n
                continue
            _remember(counts, last, recent, last[0], last[1], last[2],
                      _model_distance(quadric, has_quadric, p0, scale, last[0], last[1], last[2]), jump)
            if pending_at >= 0:
                keep[pending_at] = True
                n_kept += 1
            else:
                took_pending = True
            counts[G_REFERENCE] = REF_KEPT
        else:
            near = jump <= max_jump and d <= gate
            counts[G_RUN] = 0 if near else counts[G_RUN] + 1
            keep[n] = near or counts[G_RUN] > params[G_MAX_CONSECUTIVE]  # a long run of far points is retina
            if not keep[n]:
                counts[G_N_REJECTED] += 1
                continue
        _remember(counts, last, recent, px, py, pz, d, jump)
        n_kept += 1
    return n_kept, took_pending


@njit(cache=True)
def fit_summary(S, sf_state, sf_ok, v_ef, ef_ok, radii, prev_radii, has_prev, v_sf, scale):
    """(sphere residual mm, ellipsoid residual mm, axis change) of one update of the
    adaptive model: the RMS distances (Taubin, taubin_residuals) over the points of S of
    the sphere (state [c, r^2 - |c|^2] in the fits' coordinates scaled by `scale` mm; its
    quadric is written to v_sf (10,)) and of the ellipsoid v_ef (NaN for a fit that is
    not ok), and the largest relative change of the sorted semi-axes `radii` since
    `prev_radii` (NaN unless `has_prev` and ef_ok); prev_radii then holds the sorted
    radii (the caller keeps has_prev = ef_ok)."""
    V = np.empty((2, 10))
    k = 0
    if sf_ok:
        cx, cy, cz, c = sf_state[0], sf_state[1], sf_state[2], sf_state[3]
        v_sf[0], v_sf[1], v_sf[2], v_sf[3], v_sf[4], v_sf[5] = 1.0, 1.0, 1.0, 0.0, 0.0, 0.0
        v_sf[6], v_sf[7], v_sf[8], v_sf[9] = -cx, -cy, -cz, -c
        V[k] = v_sf
        k += 1
    if ef_ok:
        V[k] = v_ef
        k += 1
    res = scale * taubin_residuals(S, V[:k])
    sf_res = res[0] if sf_ok else np.nan
    ef_res = res[k - 1] if ef_ok else np.nan
    axis_change = np.nan
    if ef_ok:
        r = np.sort(radii)
        if has_prev:
            axis_change = 0.0
            for i in range(3):
                axis_change = max(axis_change, abs(r[i] - prev_radii[i]) / prev_radii[i])
        prev_radii[:] = r
    return sf_res, ef_res, axis_change


@njit(cache=True)
def spread_check_due(checked_at, n, recheck):
    """Whether the fit of n points runs the collinear/coplanar test, the last passed one
    at `checked_at` points (0: none): adding points only widens a cloud's scatter about
    its mean, so once spread in 3-D it stays so; the test is still repeated every
    `recheck` points (models.ellipsoid_fit.IncrementalEllipsoidFit)."""
    return checked_at == 0 or n - checked_at >= recheck


# the layout of packet_update's output vector `out`
OUT_STATE, OUT_V_SF, OUT_V_EF, OUT_CENTER, OUT_RADII, OUT_ROTATION, OUT_SF_CENTER, OUT_SIZE = 0, 4, 14, 24, 27, 30, 39, 42


@njit(cache=True)
def packet_update(P, n, p0, gate_on, quadric, has_quadric, g_params, g_counts, g_last, g_scales, g_recent,
                  Y, y, S, checked_at, recheck, X, block_r, diameter, prev_radii, has_prev, scale, kept, out):
    """The adaptive model's update by the points P (N, 3) mm (one A-scan's or a packet's), in
    one call: the kernels of the batch update, in its order. A model of n points, p0 (mm)
    the origin of every part (its first point; when n = 0 the first point kept here is
    written to p0), skips the non-finite rows of P, gates the others (gate_points, when
    `gate_on`; `quadric` the current model about p0) and copies those it keeps to
    kept[:K] (kept: (N + 1, 3): the gate may add its pending first point); if K > 0 it absorbs
    them into the sphere filter (Y, y), the scatter matrix S and the scan range (X with
    room for K more rows, block_r, `diameter` mm), refits the ellipsoid (with the spread
    test when spread_check_due(checked_at, n + K, recheck)) and summarises the fits
    (fit_summary), all state updated in place.

    Returns (non-finite count, K, spread test run, sphere ok, fit status code, diameter mm,
    sphere residual mm, ellipsoid residual mm, axis change, sphere radius mm); with K > 0,
    `out` (OUT_SIZE,) receives the sphere state, the sphere's quadric, the fit's quadric,
    centre, semi-axes and rotation (row-major), and the sphere's centre (mm).
    """
    m = 0
    for i in range(P.shape[0]):  # row 0 is left for the gate's pending first point
        if np.isfinite(P[i, 0]) and np.isfinite(P[i, 1]) and np.isfinite(P[i, 2]):
            kept[m + 1, 0], kept[m + 1, 1], kept[m + 1, 2] = P[i, 0], P[i, 1], P[i, 2]
            m += 1
    n_nonfinite, k = P.shape[0] - m, 0
    keep = np.ones(m, np.bool_)
    if gate_on and m > 0:
        pending_x, pending_y, pending_z = g_last[0], g_last[1], g_last[2]
        if gate_points(kept[1:m + 1], keep, quadric, has_quadric, p0, scale, n, g_params, g_counts, g_last,
                       g_scales, g_recent)[1]:
            kept[0, 0], kept[0, 1], kept[0, 2] = pending_x, pending_y, pending_z
            k = 1
    for i in range(m):
        if keep[i]:
            kept[k, 0], kept[k, 1], kept[k, 2] = kept[i + 1, 0], kept[i + 1, 1], kept[i + 1, 2]
            k += 1
    if k == 0:
        return n_nonfinite, 0, False, False, 0, diameter, np.nan, np.nan, np.nan, np.nan
    A = kept[:k]
    if n == 0:
        p0[0], p0[1], p0[2] = A[0, 0], A[0, 1], A[0, 2]
    state, sf_ok = sphere_absorb(Y, y, A, p0, scale, n + k)
    add_design_rows(S, A, p0, scale)
    diameter = diameter_after_adding(X, block_r, n, A, p0, diameter)
    check = spread_check_due(checked_at, n + k, recheck)
    code, v, center, radii, R = fit_ellipsoid_scatter(S, p0, scale, check)
    v_sf = out[OUT_V_SF:OUT_V_EF]
    sf_res, ef_res, axis_change = fit_summary(S, state, sf_ok, v, code == 0, radii, prev_radii, has_prev, v_sf, scale)
    out[OUT_STATE:OUT_V_SF] = state
    out[OUT_V_EF:OUT_CENTER] = v
    out[OUT_CENTER:OUT_RADII] = center
    out[OUT_RADII:OUT_ROTATION] = radii
    out[OUT_ROTATION:OUT_SF_CENTER] = R.ravel()
    radius = sphere_center_radius(state, p0, scale, out[OUT_SF_CENTER:OUT_SIZE]) if sf_ok else np.nan
    return n_nonfinite, k, check, sf_ok, code, diameter, sf_res, ef_res, axis_change, radius
