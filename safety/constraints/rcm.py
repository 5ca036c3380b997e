"""Remote centre of motion: the shaft pivots about the trocar.

The shaft's material point at the trocar C (group "trocar": one point, the body I's
x axis along the shaft) may move only along the shaft: its velocity along the shaft's
two lateral axes (columns 1 and 2 of R_WI) is zero, and the lateral error e (mm) of the
shaft from C decays as de/dt = -gain e (drift correction):

    n_a . J_C qdot = gain n_a . (p_WC - p_WI),   a = 1, 2.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from safety.constraints.base import Constraint, as_params, check_finite_positive


@njit(cache=True)
def fill_rcm(sp, J, start, R_WI, p_WI, A, b, p):
    """sp = [p_WC (3) mm, gain 1/s]: two rows A qdot = b for the point J[start]."""
    n = J.shape[2]
    d0, d1, d2 = sp[0] - p_WI[0], sp[1] - p_WI[1], sp[2] - p_WI[2]
    for a in range(2):
        e = R_WI[0, a + 1] * d0 + R_WI[1, a + 1] * d1 + R_WI[2, a + 1] * d2
        b[p] = sp[3] * e
        for j in range(n):
            A[p, j] = (R_WI[0, a + 1] * J[start, 0, j] + R_WI[1, a + 1] * J[start, 1, j]
                       + R_WI[2, a + 1] * J[start, 2, j])
        p += 1
    return p


@dataclass(frozen=True, eq=False)
class RcmEquality(Constraint):
    """The shaft passes through the trocar p_WC (3,) mm in W, drift corrected at gain_per_s."""

    p_WC: np.ndarray
    gain_per_s: float
    group: str = "trocar"
    name: str = "rcm"

    kind = "equality"
    filler = staticmethod(fill_rcm)
    intervenes = False

    def __post_init__(self):
        check_finite_positive("RcmEquality", gain_per_s=self.gain_per_s)
        if np.shape(self.p_WC) != (3,) or not np.all(np.isfinite(self.p_WC)):
            raise ValueError(f"RcmEquality.p_WC must be 3 finite mm, got {self.p_WC}")

    def params(self) -> np.ndarray:
        return as_params(self.p_WC, self.gain_per_s)

    def max_rows(self, group_size: int) -> int:
        return 2
