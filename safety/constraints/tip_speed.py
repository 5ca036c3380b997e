"""Tip speed limit: |J_tip qdot| <= v_max (mm/s) as 26 half-spaces inside the ball.

The faces of the polytope are the cube's faces, edges and corners (26 unit normals).
With every face at distance d the polytope holds the ball of radius d and lies within
the ball of radius 1.13 d (the maximum over directions, by linear programming); faces
at v_max / REACH keep the speed <= v_max and allow at least 0.87 v_max in any
direction.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from safety.constraints.base import Constraint, as_params, check_finite_positive

FACE_NORMALS = np.array([v for v in np.ndindex(3, 3, 3) if v != (1, 1, 1)], dtype=float) - 1.0
FACE_NORMALS /= np.linalg.norm(FACE_NORMALS, axis=1, keepdims=True)
REACH = 1.15


@njit(cache=True)
def fill_tip_speed(sp, J_tip, G, h, ids, m, id0):
    """The polytope's rows D_i . J_tip qdot <= sp[0] / REACH (sp[0]: v_max mm/s)."""
    D = FACE_NORMALS
    n = J_tip.shape[1]
    for i in range(D.shape[0]):
        for j in range(n):
            G[m, j] = D[i, 0] * J_tip[0, j] + D[i, 1] * J_tip[1, j] + D[i, 2] * J_tip[2, j]
        h[m] = sp[0] / REACH
        ids[m] = id0 + i
        m += 1
    return m


@dataclass(frozen=True)
class TipSpeedLimit(Constraint):
    """The tip's speed stays at or below `max_speed_mm_s`."""

    max_speed_mm_s: float = 20.0
    name: str = "tip_speed"

    kind = "inequality"
    filler = staticmethod(fill_tip_speed)

    def __post_init__(self):
        check_finite_positive("TipSpeedLimit", max_speed_mm_s=self.max_speed_mm_s)

    @property
    def every_direction_mm_s(self) -> float:
        """The speed (mm/s) the polytope allows in every direction: max_speed_mm_s / REACH."""
        return self.max_speed_mm_s / REACH

    def params(self) -> np.ndarray:
        return as_params(self.max_speed_mm_s)

    def max_rows(self, group_size: int) -> int:
        return FACE_NORMALS.shape[0]

    def row_name(self, index: int, point_names: tuple) -> str:
        return self.name
