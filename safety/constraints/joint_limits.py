"""Joint position limits as velocity bounds: each joint approaches [q_min + margin,
q_max - margin] no faster than gain x its distance to that interval (rad, rad/s)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from safety.constraints.base import Constraint, as_params, check_finite_positive


@njit(cache=True)
def fill_joint_position(sp, q, lb, ub):
    """sp = [gain 1/s, margin rad, q_min (n), q_max (n)]: lb_j >= -gain (q_j - (q_min_j +
    margin)), ub_j <= gain ((q_max_j - margin) - q_j)."""
    n = q.shape[0]
    gain, margin = sp[0], sp[1]
    for a in range(n):
        lb[a] = max(lb[a], -gain * (q[a] - (sp[2 + a] + margin)))
        ub[a] = min(ub[a], gain * ((sp[2 + n + a] - margin) - q[a]))


@dataclass(frozen=True, eq=False)
class JointPositionLimits(Constraint):
    """Joint angles stay within [q_min + margin_rad, q_max - margin_rad] (rad)."""

    q_min: np.ndarray
    q_max: np.ndarray
    gain_per_s: float = 10.0
    margin_rad: float = float(np.radians(2.0))
    name: str = "joint_position"

    kind = "bounds"
    filler = staticmethod(fill_joint_position)
    intervenes = False

    def __post_init__(self):
        check_finite_positive("JointPositionLimits", gain_per_s=self.gain_per_s)
        check_finite_positive("JointPositionLimits", allow_zero=True, margin_rad=self.margin_rad)
        if np.shape(self.q_min) != np.shape(self.q_max) or np.ndim(self.q_min) != 1:
            raise ValueError(f"JointPositionLimits: q_min and q_max must be (n,) rad, got {np.shape(self.q_min)} "
                             f"and {np.shape(self.q_max)}")
        if np.isnan(np.asarray(self.q_min, dtype=float)).any() or np.isnan(np.asarray(self.q_max, dtype=float)).any():
            raise ValueError("JointPositionLimits: q_min and q_max must not be NaN (rad; -inf / +inf: no limit that way)")

    def params(self) -> np.ndarray:
        return as_params(self.gain_per_s, self.margin_rad, self.q_min, self.q_max)
