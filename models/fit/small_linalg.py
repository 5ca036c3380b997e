"""Compiled linear algebra on the fits' few-by-few matrices (3x3 to 10x10), hand-written
where np.linalg inside numba is materially slower at these sizes or not what the callers
need.

Per call on warm compiled code, hand-written / np.linalg in nopython mode
(bench/bench_model_update.py, `small_linalg_figures`): Cholesky 0.05 / 0.13 us (4x4),
0.12 / 0.22 us (6x6); the inverse of a lower-triangular factor 0.07 / 0.69 us (4x4),
0.09 / 0.61 us (6x6, np.linalg.inv); a pivoted solve 0.13 / 0.39 us (4x4), 0.18 / 0.46 us
(6x6, np.linalg.solve); the symmetric eigensolver 0.6-0.7 / 0.85-0.9 us on a fit's 3x3
matrices, 1.2 / 1.6-1.7 us at 4x4, and about as fast as np.linalg.eigh at 6x6 (2.7-3.8 us
each, from run to run), where it is kept for its accuracy (eigh_sym). np.linalg also raises where the
callers want an answer: on a matrix that is not positive definite (degenerate data) or
singular (a shift at an eigenvalue, a singular KKT system in safety.qp).
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def mat_vec(A, x):
    """A @ x by loops: for these few-by-few matrices a BLAS call's overhead exceeds the work."""
    y = np.zeros(A.shape[0])
    for i in range(A.shape[0]):
        s = 0.0
        for j in range(A.shape[1]):
            s += A[i, j] * x[j]
        y[i] = s
    return y


@njit(cache=True)
def dot(a, b):
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * b[i]
    return s


@njit(cache=True)
def cholesky(A):
    """(L, ok): the lower Cholesky factor of the symmetric A (n, n); not ok when A is not
    positive definite (an answer, not an exception: a singular matrix is degenerate data).
    np.linalg.cholesky takes 2-2.5 x as long at 4x4-6x6 and raises instead."""
    L = np.zeros(A.shape)
    return L, cholesky_into(A, L)


@njit(cache=True)
def cholesky_into(A, L):
    """cholesky(A) written into L (n, n) (its upper triangle zeroed); returns ok: for callers
    that factor many small matrices in a loop and reuse one buffer."""
    n = A.shape[0]
    L[:, :] = 0.0
    for j in range(n):
        acc = 0.0  # the sums run in index order, from 0: no temporary arrays
        for k in range(j):
            acc += L[j, k] * L[j, k]
        s = A[j, j] - acc
        if not s > 1e-300:
            return False
        L[j, j] = np.sqrt(s)
        for i in range(j + 1, n):
            acc = 0.0
            for k in range(j):
                acc += L[i, k] * L[j, k]
            L[i, j] = (A[i, j] - acc) / L[j, j]
    return True


@njit(cache=True)
def eigh_sym(A):
    """(eigenvalues ascending (n,), eigenvectors as columns (n, n)) of the symmetric A, by
    cyclic Jacobi rotations (Golub & Van Loan 8.5), accurate to rounding. On a fit's 3x3
    matrices np.linalg.eigh takes 1.3-1.5 x as long (0.85-0.9 against 0.6-0.7 us); at 6x6
    it is about as fast (2.7-3.8 us each) but LAPACK's small eigenvalues are accurate only
    to rounding of the largest, where Jacobi's are accurate relative to themselves: the
    exact-quadric test and the null vector of a near-singular S' (models.fit.quadric_kernels)
    rest on them, and with np.linalg.eigh the robust fit's histories on the paper spiral
    moved by up to 4e-4 mm (its least-squares ones stayed bit-identical)."""
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
def lower_inverse(L):
    """L^-1 of the lower-triangular L (n, n) with a positive diagonal, by forward
    substitution: np.linalg.inv takes 7-9 x as long at 4x4-6x6."""
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
def pivoted_solve(A, b, tiny):
    """x with A x = b for A (n, n) (overwritten), by Gaussian elimination with partial
    pivoting; a pivot below `tiny` is replaced by `tiny` (for a shift at an eigenvalue,
    where the near-singular solve is the point: its answer is the eigenvector). A singular
    A gives huge or non-finite entries, never an exception (safety.qp checks the residual);
    np.linalg.solve raises there and takes 2.5-3 x as long at 4x4-6x6."""
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
