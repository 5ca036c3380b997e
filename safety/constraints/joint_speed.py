"""Joint speed limits: |qdot_j| <= qdot_max_j (rad/s)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from safety.constraints.base import Constraint, as_params


@njit(cache=True)
def fill_joint_speed(sp, lb, ub):
    """sp = qdot_max (n,) rad/s: lb_j >= -qdot_max_j, ub_j <= qdot_max_j."""
    for a in range(lb.shape[0]):
        lb[a] = max(lb[a], -sp[a])
        ub[a] = min(ub[a], sp[a])


@dataclass(frozen=True, eq=False)
class JointSpeedLimits(Constraint):
    """Each joint's speed stays at or below qdot_max (n,) rad/s."""

    qdot_max: np.ndarray
    name: str = "joint_speed"

    kind = "bounds"
    filler = staticmethod(fill_joint_speed)
    intervenes = False

    def __post_init__(self):
        v = np.asarray(self.qdot_max, dtype=float)
        if v.ndim != 1 or not (np.all(np.isfinite(v)) and np.all(v > 0)):
            raise ValueError(f"JointSpeedLimits.qdot_max must be (n,) finite rad/s > 0, got {self.qdot_max}")

    def params(self) -> np.ndarray:
        return as_params(self.qdot_max)
