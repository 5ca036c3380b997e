"""The distance-field interface of the shapes a safety filter keeps the tool inside.

A field answers, for points P (M, 3) mm in its frame, the signed distance to its
surface (mm, > 0 inside), the distance's unit gradient (pointing inward, the direction
of increasing distance) and an uncertainty: a one-sided bound (mm) on how much the field
may overstate the distance at each point (0 for an exact shape). `field_kernel()` gives
the same answers as a compiled function and its parameters, for callers that are
compiled themselves.
"""
from __future__ import annotations

from typing import Callable, NamedTuple, Protocol, runtime_checkable

import numpy as np
from numba import njit


class FieldKernel(NamedTuple):
    """A compiled field: `kernel(params, P) -> (h (M,) mm, g (M, 3), u (M,) mm)`, a
    module-level @njit(cache=True) function of `params` (a C-contiguous, writeable float64
    (K,) array, made once per shape) and the points P (M, 3) mm (float64, C-contiguous).
    A non-finite point gives NaN distance and gradient and an infinite uncertainty, never
    an exception."""

    kernel: Callable
    params: np.ndarray


@runtime_checkable
class DistanceField(Protocol):
    """Signed distance (mm, > 0 inside), unit gradient and uncertainty (mm) of points P
    (M, 3) mm in the field's frame; `field_kernel()` the compiled form of the same."""

    def signed_distance(self, P) -> np.ndarray:
        """(M,) signed distance mm, > 0 inside."""

    def gradient(self, P) -> np.ndarray:
        """(M, 3) unit gradient of the signed distance (inward)."""

    def signed_distance_and_gradient(self, P) -> tuple[np.ndarray, np.ndarray]:
        """((M,) signed distance mm, (M, 3) unit gradient)."""

    def uncertainty(self, P) -> np.ndarray:
        """(M,) bound (mm) on how much the signed distance may overstate the true one."""

    def field_kernel(self) -> FieldKernel:
        """The compiled field (FieldKernel)."""


class KernelQueries:
    """DistanceField's queries derived from one method, `signed_distance_gradient_uncertainty(P)`
    -> ((M,) mm, (M, 3), (M,) mm), for the fields that evaluate all three in one compiled call."""

    def signed_distance(self, P) -> np.ndarray:
        """(M,) signed distance mm, > 0 inside."""
        return self.signed_distance_gradient_uncertainty(P)[0]

    def gradient(self, P) -> np.ndarray:
        """(M, 3) unit gradient of the signed distance (inward)."""
        return self.signed_distance_gradient_uncertainty(P)[1]

    def signed_distance_and_gradient(self, P) -> tuple[np.ndarray, np.ndarray]:
        """((M,) signed distance mm, (M, 3) unit gradient)."""
        return self.signed_distance_gradient_uncertainty(P)[:2]

    def uncertainty(self, P) -> np.ndarray:
        """(M,) standard deviation (mm) of the surface at each point; +inf for a non-finite point."""
        return self.signed_distance_gradient_uncertainty(P)[2]


@njit(cache=True)
def finite_row(P, m) -> bool:
    """Whether the point in row m of P (M, 3) is finite (the fields answer NaN otherwise)."""
    return np.isfinite(P[m, 0]) and np.isfinite(P[m, 1]) and np.isfinite(P[m, 2])


@njit(cache=True)
def unanswered(P, h, g, u):
    """(h, g, u) with NaN, NaN and +inf at the non-finite rows of P (M, 3): a field's answer
    where it has none (for kernels whose other answers ignore the point's finiteness)."""
    for i in range(P.shape[0]):
        if not finite_row(P, i):
            h[i], u[i] = np.nan, np.inf
            g[i, 0] = g[i, 1] = g[i, 2] = np.nan
    return h, g, u


@njit(cache=True)
def field_outputs(P):
    """(h (M,), g (M, 3), finite (M,) bool): a field's output arrays for the points P (M, 3)
    mm, NaN in the rows of the non-finite points (the field's answer there) and 0 in the
    others, and which rows are finite."""
    M = P.shape[0]
    h, g, finite = np.zeros(M), np.zeros((M, 3)), np.ones(M, dtype=np.bool_)
    for m in range(M):
        if not finite_row(P, m):
            h[m] = g[m, 0] = g[m, 1] = g[m, 2] = np.nan
            finite[m] = False
    return h, g, finite


@njit(cache=True)
def exact_uncertainty(P):
    """(M,) the uncertainty (mm) of an exact field at the points P (M, 3) mm: 0, and +inf
    where a point is not finite."""
    u = np.zeros(P.shape[0])
    for m in range(P.shape[0]):
        if not finite_row(P, m):
            u[m] = np.inf
    return u


def field_params(*parts) -> np.ndarray:
    """A FieldKernel's params: the parts (floats or arrays, row-major) in one new
    C-contiguous, writeable float64 array."""
    return np.ascontiguousarray(np.concatenate([np.ravel(np.asarray(p, dtype=float)) for p in parts]))
