"""Point barrier: monitored points keep a clearance from a distance field.

For each point p of its group the field gives the signed distance h(p) (mm, > 0 on the
kept side), its unit gradient and its uncertainty u(p) (mm). The point must keep
h >= h_min = d_safe + k u + c, with c the declared bound of the sensor calibration's
error on the model (`calibration_mm`: a model built from the points of a mis-calibrated
sensor lies off the retina by up to c: FilterConfig.calibration_margin_mm). A control barrier row
enforces it at the joint-velocity level: grad . J_p qdot >= -gain (h - h_min) (gain 1/s),
grad the field's gradient: the distance's, or, where u varies over space (the local
model's barrier form, models.local.field_kernels.local_field), that of h - k u, so
that the row holds the rate of the bound itself. Below h_min (a model update can move the boundary past a point) the point
must recover at gain (h_min - h), capped at `max_recovery_mm_s`, a rate the speed
limits can give, so that the QP stays feasible instead of refusing every step.

A row further from its bound than `screen_reach_mm` (what the tip speed limit can close
at the barrier's rate within its horizon: v_max / gain) cannot become active in this
step and is left out of the QP; the first `always_first` points of the group (the tip
and the cutter port: the clearance and the cutter interlock) are always kept. A field
that answers +inf at a point puts no boundary there (no row, no clearance). A NaN
distance, a non-finite gradient, or a NaN or negative uncertainty refuses the step.

The filler reports each point's clearance h (`point_h`) and the bound on its TRUE
clearance that the rule assumes, h - k u - c (`point_bound`): where the true retina lies
nearer than that, the field's uncertainty or the calibration bound was not honest there
(the closed loop measures it against the true eye: eval.clearance.bound_excess).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from safety.constraints.base import Constraint, as_params, check_finite_positive

NON_FINITE_FIELD = 1  # the filler's fault code


@njit(cache=True)
def fill_point_barrier(sp, P, J, start, stop, fh, fg, fu, G, h, ids, m, id0, point_h, point_bound):
    """sp = [side (+1: keep inside the field, -1: keep outside), d_safe mm, k, gain 1/s,
    max recovery mm/s, screen reach mm, always_first, calibration bound mm]; the rows of
    the group's points P[start:stop] (Jacobians J) from the field's values fh, fg, fu there;
    point_h the points' clearance h, point_bound the true clearance the rule assumes, h_min - d_safe below h."""
    side, d_safe, k_sigma, gain, max_recovery, reach, always_first = sp[0], sp[1], sp[2], sp[3], sp[4], sp[5], sp[6]
    calibration = sp[7]
    n = J.shape[2]
    for i in range(stop - start):
        if fh[i] == np.inf and side > 0.0:  # no boundary at this point
            point_h[start + i] = np.inf
            point_bound[start + i] = np.inf
            continue
        hi = side * fh[i]
        g0, g1, g2 = side * fg[i, 0], side * fg[i, 1], side * fg[i, 2]
        if not (np.isfinite(hi) and np.isfinite(g0) and np.isfinite(g1) and np.isfinite(g2)
                and np.isfinite(fu[i]) and fu[i] >= 0.0):
            return -NON_FINITE_FIELD
        h_min = d_safe + k_sigma * fu[i] + calibration
        point_h[start + i] = hi
        point_bound[start + i] = hi - (h_min - d_safe)
        if hi - h_min <= reach or i < always_first:
            r = start + i
            for j in range(n):  # -(grad . J) qdot <= gain (h - h_min), the recovery below h_min capped
                G[m, j] = -(g0 * J[r, 0, j] + g1 * J[r, 1, j] + g2 * J[r, 2, j])
            h[m] = max(gain * (hi - h_min), -max_recovery)
            ids[m] = id0 + i
            m += 1
    return m


@dataclass(frozen=True)
class PointBarrier(Constraint):
    """The points of `group` stay at least d_safe_mm + sigma_factor x the field's
    uncertainty + calibration_mm inside the distance field in slot `field` (mm, 1/s)."""

    group: str
    field: str
    d_safe_mm: float = 0.5
    gain_per_s: float = 20.0
    max_recovery_mm_s: float = 5.0
    screen_reach_mm: float = np.inf
    always_first: int = 0
    sigma_factor: float = 1.0
    max_points: int = 64
    name: str = "boundary"
    calibration_mm: float = 0.0

    kind = "inequality"
    filler = staticmethod(fill_point_barrier)
    side = 1.0
    reports_clearance = True

    def __post_init__(self):
        check_finite_positive(type(self).__name__, gain_per_s=self.gain_per_s, max_recovery_mm_s=self.max_recovery_mm_s)
        check_finite_positive(type(self).__name__, allow_zero=True, d_safe_mm=self.d_safe_mm,
                              sigma_factor=self.sigma_factor, calibration_mm=self.calibration_mm)
        if not (self.screen_reach_mm > 0):
            raise ValueError(f"{type(self).__name__}.screen_reach_mm must be > 0 mm (inf: keep every row), "
                             f"got {self.screen_reach_mm}")
        if not (isinstance(self.max_points, int) and self.max_points >= 1):
            raise ValueError(f"{type(self).__name__}.max_points must be an int >= 1, got {self.max_points}")
        if not (isinstance(self.always_first, int) and self.always_first >= 0):
            raise ValueError(f"{type(self).__name__}.always_first must be an int >= 0, got {self.always_first}")

    def params(self) -> np.ndarray:
        return as_params(self.side, self.d_safe_mm, self.sigma_factor, self.gain_per_s, self.max_recovery_mm_s,
                         self.screen_reach_mm, self.always_first, self.calibration_mm)

    def max_rows(self, group_size: int) -> int:
        return group_size

    def fault_reason(self, code: int) -> str:
        return "model returned non-finite distance or gradient"
