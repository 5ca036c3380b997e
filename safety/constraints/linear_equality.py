"""Given equality rows A qdot = b (for example RCM rows computed elsewhere)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from safety.constraints.base import Constraint, as_params


@njit(cache=True)
def fill_linear_equality(sp, q, A, b, p):
    """sp = [rows r, A (r x n) row-major, b (r)]."""
    n = q.shape[0]
    r = int(sp[0])
    for i in range(r):
        for j in range(n):
            A[p, j] = sp[1 + i * n + j]
        b[p] = sp[1 + r * n + i]
        p += 1
    return p


@dataclass(frozen=True, eq=False)
class LinearEquality(Constraint):
    """Rows A (r, n) qdot = b (r,) (rad/s in, the rows' units out)."""

    A: np.ndarray
    b: np.ndarray
    name: str = "rcm"

    kind = "equality"
    filler = staticmethod(fill_linear_equality)
    intervenes = False

    def __post_init__(self):
        A, b = np.atleast_2d(np.asarray(self.A, dtype=float)), np.atleast_1d(np.asarray(self.b, dtype=float))
        if A.ndim != 2 or b.shape != (A.shape[0],):
            raise ValueError(f"LinearEquality: A must be (r, n) and b (r,), got {np.shape(self.A)} and {np.shape(self.b)}")
        object.__setattr__(self, "A", A)
        object.__setattr__(self, "b", b)

    def params(self) -> np.ndarray:
        return as_params(self.A.shape[0], self.A, self.b)

    def max_rows(self, group_size: int) -> int:
        return self.A.shape[0]
