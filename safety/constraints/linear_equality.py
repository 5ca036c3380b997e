"""Given equality rows A qdot = b (for example RCM rows computed elsewhere), and the
planned stop their maker decided for the step (`refusal`), if any."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from safety.constraints.base import Constraint, as_params

REFUSED = 1  # the filler's fault code


@njit(cache=True)
def fill_linear_equality(sp, q, A, b, p):
    """sp = [rows r, A (r x n) row-major, b (r), refused 1/0]; -REFUSED when refused."""
    n = q.shape[0]
    r = int(sp[0])
    if sp[1 + r * n + r] != 0.0:
        return -REFUSED
    for i in range(r):
        for j in range(n):
            A[p, j] = sp[1 + i * n + j]
        b[p] = sp[1 + r * n + i]
        p += 1
    return p


@dataclass(frozen=True, eq=False)
class LinearEquality(Constraint):
    """Rows A (r, n) qdot = b (r,) (rad/s in, the rows' units out); a non-empty `refusal`
    refuses the step with it as the reason; `drift_correction`: b corrects a drift (the
    RCM's rows: gain x the lateral error), which a step with no other solution may scale
    down (safety.stack)."""

    A: np.ndarray
    b: np.ndarray
    name: str = "rcm"
    refusal: str = ""
    drift_correction: bool = False

    kind = "equality"
    filler = staticmethod(fill_linear_equality)
    intervenes = False

    def __post_init__(self):
        A, b = np.atleast_2d(np.asarray(self.A, dtype=float)), np.atleast_1d(np.asarray(self.b, dtype=float))
        if A.ndim != 2 or b.shape != (A.shape[0],):
            raise ValueError(f"LinearEquality: A must be (r, n) and b (r,), got {np.shape(self.A)} and {np.shape(self.b)}")
        if not (np.isfinite(A).all() and np.isfinite(b).all()):
            raise ValueError("LinearEquality: A and b must be finite")
        object.__setattr__(self, "A", A)
        object.__setattr__(self, "b", b)

    def params(self) -> np.ndarray:
        return as_params(self.A.shape[0], self.A, self.b, 1.0 if self.refusal else 0.0)

    def max_rows(self, group_size: int) -> int:
        return self.A.shape[0]

    def fault_reason(self, code: int) -> str:
        if code == REFUSED and self.refusal:
            return self.refusal
        return super().fault_reason(code)
