"""Argument checks shared by the models package: clear ValueErrors, never silent coercion."""
from __future__ import annotations

import math

import numpy as np
from numba import njit


def _all_finite(a: np.ndarray) -> bool:
    """Whether every entry of the float array `a` is finite (for small arrays: scalar
    checks, cheaper than np.isfinite's temporary)."""
    return all(map(math.isfinite, a.ravel().tolist()))


@njit(cache=True)
def _orthonormality_error_and_det(A):
    """(max |A^T A - I|, det A) of a (3, 3) matrix."""
    err = 0.0
    for i in range(3):
        for j in range(3):
            g = A[0, i] * A[0, j] + A[1, i] * A[1, j] + A[2, i] * A[2, j] - (1.0 if i == j else 0.0)
            err = max(err, abs(g))
    det = (A[0, 0] * (A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]) - A[0, 1] * (A[1, 0] * A[2, 2] - A[1, 2] * A[2, 0])
           + A[0, 2] * (A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]))
    return err, det


def as_points(P, name: str = "P", *, allow_nonfinite: bool = False) -> np.ndarray:
    """Return P as a float (N, 3) array; a single (3,) point becomes (1, 3).

    Raises ValueError naming `name` when the shape is not (N, 3) or (3,), or when a
    value is NaN/inf (unless `allow_nonfinite`).
    """
    try:
        A = np.asarray(P, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be an (N, 3) array of numbers (points in mm), got {type(P).__name__}") from None
    if A.ndim == 1 and A.shape[0] == 3:
        A = A[None, :]
    if A.ndim != 2 or A.shape[1] != 3:
        raise ValueError(f"{name} must be an (N, 3) array of points in mm, got shape {np.shape(P)}")
    if not allow_nonfinite and not np.all(np.isfinite(A)):
        raise ValueError(f"{name} contains NaN or inf; every coordinate must be finite (mm)")
    return A


def as_beams(B, n: int, name: str = "beam_W") -> np.ndarray:
    """Return B, the beams' directions of n points, as a C-contiguous float (n, 3) array
    (a single (3,) direction becomes (1, 3)); ValueError naming `name` when it is not n
    rows of 3. Its rows need not be unit vectors: the model normalises them, and takes a
    row that is not finite or is shorter than 0.5 as no beam for that point."""
    if type(B) is np.ndarray and B.dtype == np.float64 and B.shape == (n, 3) and B.flags.c_contiguous:
        return B
    A = as_points(B, name, allow_nonfinite=True)
    if len(A) != n:
        raise ValueError(f"{name} must hold one beam direction per point: {n} rows, got {len(A)}")
    return np.ascontiguousarray(A)


def as_vector3(v, name: str) -> np.ndarray:
    """Return v as a finite float (3,) array, or raise ValueError naming `name`."""
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a (3,) vector of numbers, got {type(v).__name__}") from None
    if a.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {a.shape}")
    if not _all_finite(a):
        raise ValueError(f"{name} must be finite, got {a}")
    return a


def as_positive(x, name: str) -> float:
    """Return x as a finite float > 0, or raise ValueError naming `name`."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {x!r}") from None
    if not np.isfinite(v) or v <= 0.0:
        raise ValueError(f"{name} must be finite and > 0, got {x!r}")
    return v


def as_rotation(R, name: str = "rotation", tol: float = 1e-9) -> np.ndarray:
    """Return R as a (3, 3) proper rotation matrix (R^T R = I within `tol`, det = +1)."""
    A = np.asarray(R, dtype=float)
    if A.shape != (3, 3):
        raise ValueError(f"{name} must be a (3, 3) rotation matrix, got shape {A.shape}")
    if not _all_finite(A):
        raise ValueError(f"{name} must be finite")
    err, det = _orthonormality_error_and_det(np.ascontiguousarray(A))
    if err > tol:
        raise ValueError(f"{name} is not orthonormal: max |R^T R - I| = {err:.3g} > {tol:g}")
    if det < 0:
        raise ValueError(f"{name} is a reflection (det = -1); a proper rotation has det = +1")
    return A


def check_positive(owner, *names: str, allow_zero: bool = False) -> None:
    """Raise ValueError unless each attribute `name` of `owner` is finite and > 0 (>= 0)."""
    for name in names:
        v = getattr(owner, name)
        ok = isinstance(v, (int, float, np.floating, np.integer)) and np.isfinite(v) and (v >= 0 if allow_zero else v > 0)
        if not ok:
            raise ValueError(f"{name} must be finite and {'>=' if allow_zero else '>'} 0, got {v!r}")


def check_count(owner, *names: str, minimum: int = 0) -> None:
    """Raise ValueError unless each attribute `name` of `owner` is an integer >= minimum."""
    for name in names:
        v = getattr(owner, name)
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < minimum:
            raise ValueError(f"{name} must be an integer >= {minimum}, got {v!r}")
