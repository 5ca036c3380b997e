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

While a point is inside its margin (recovering), the barrier row bounds only its speed
along the gradient; with a finite `max_slide_mm_s` four more rows bound its speed along
the surface (each of two directions perpendicular to the gradient) to that. A model
update can leave a point inside its margin where the model's surface normal is off the
true retina's: backing out along it while sliding along the wall at the tool's speed can
close on the true retina (the local model on a detachment's flank, 67-70 deg off:
models.local). Held to a slow slide, the point backs out before it moves on.

A row further from its bound than `screen_reach_mm` (what the tip speed limit can close
at the barrier's rate within its horizon: v_max / gain) cannot become active in this
step and is left out of the QP; the first `always_first` points of the group (the tip
and the cutter port: the clearance and the cutter interlock) are always kept. A field
that answers +inf at a point puts no boundary there (no row, no clearance). A NaN
distance, a non-finite gradient, or a NaN or negative uncertainty refuses the step.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from safety.constraints.base import Constraint, as_params, check_finite_positive

NON_FINITE_FIELD = 1  # the filler's fault code


@njit(cache=True)
def fill_point_barrier(sp, P, J, start, stop, fh, fg, fu, G, h, ids, m, id0, point_h):
    """sp = [side (+1: keep inside the field, -1: keep outside), d_safe mm, k, gain 1/s,
    max recovery mm/s, screen reach mm, always_first, calibration bound mm, max slide mm/s
    (inf: none)]; the rows of the group's points P[start:stop] (Jacobians J) from the
    field's values fh, fg, fu there. Point i's rows have identities id0 + stride i + r
    (stride 5 with a slide bound, else 1; r 0 the barrier row, 1-4 the slide rows)."""
    side, d_safe, k_sigma, gain, max_recovery, reach, always_first = sp[0], sp[1], sp[2], sp[3], sp[4], sp[5], sp[6]
    calibration, max_slide = sp[7], sp[8]
    stride = 5 if max_slide < np.inf else 1
    n = J.shape[2]
    for i in range(stop - start):
        if fh[i] == np.inf and side > 0.0:  # no boundary at this point
            point_h[start + i] = np.inf
            continue
        hi = side * fh[i]
        g0, g1, g2 = side * fg[i, 0], side * fg[i, 1], side * fg[i, 2]
        if not (np.isfinite(hi) and np.isfinite(g0) and np.isfinite(g1) and np.isfinite(g2)
                and np.isfinite(fu[i]) and fu[i] >= 0.0):
            return -NON_FINITE_FIELD
        h_min = d_safe + k_sigma * fu[i] + calibration
        point_h[start + i] = hi
        if hi - h_min <= reach or i < always_first:
            r = start + i
            for j in range(n):  # -(grad . J) qdot <= gain (h - h_min), the recovery below h_min capped
                G[m, j] = -(g0 * J[r, 0, j] + g1 * J[r, 1, j] + g2 * J[r, 2, j])
            h[m] = max(gain * (hi - h_min), -max_recovery)
            ids[m] = id0 + stride * i
            m += 1
            if hi < h_min and stride == 5:  # recovering: the slide along the surface bounded too
                gn = np.sqrt(g0 * g0 + g1 * g1 + g2 * g2)
                if gn > 0.0:
                    t = tangent_pair(g0 / gn, g1 / gn, g2 / gn)
                    for a in range(4):
                        s = 1.0 if a % 2 == 0 else -1.0
                        b = 3 * (a // 2)
                        for j in range(n):
                            G[m, j] = s * (t[b] * J[r, 0, j] + t[b + 1] * J[r, 1, j] + t[b + 2] * J[r, 2, j])
                        h[m] = max_slide
                        ids[m] = id0 + stride * i + 1 + a
                        m += 1
    return m


@njit(cache=True, inline="always")
def tangent_pair(u0, u1, u2):
    """(6,) two unit vectors perpendicular to the unit (u0, u1, u2) and to each other."""
    a0, a1, a2 = (1.0, 0.0, 0.0) if abs(u0) < 0.9 else (0.0, 1.0, 0.0)
    t0, t1, t2 = u1 * a2 - u2 * a1, u2 * a0 - u0 * a2, u0 * a1 - u1 * a0
    tn = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    t0, t1, t2 = t0 / tn, t1 / tn, t2 / tn
    return np.array([t0, t1, t2, u1 * t2 - u2 * t1, u2 * t0 - u0 * t2, u0 * t1 - u1 * t0])


@dataclass(frozen=True)
class PointBarrier(Constraint):
    """The points of `group` stay at least d_safe_mm + sigma_factor x the field's
    uncertainty + calibration_mm inside the distance field in slot `field` (mm, 1/s);
    a point inside that margin slides along the surface at most `max_slide_mm_s` (inf:
    no bound)."""

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
    max_slide_mm_s: float = np.inf

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
        if not (self.max_slide_mm_s > 0):
            raise ValueError(f"{type(self).__name__}.max_slide_mm_s must be > 0 mm/s (inf: no bound), "
                             f"got {self.max_slide_mm_s}")
        if not (isinstance(self.always_first, int) and self.always_first >= 0):
            raise ValueError(f"{type(self).__name__}.always_first must be an int >= 0, got {self.always_first}")

    def params(self) -> np.ndarray:
        return as_params(self.side, self.d_safe_mm, self.sigma_factor, self.gain_per_s, self.max_recovery_mm_s,
                         self.screen_reach_mm, self.always_first, self.calibration_mm, self.max_slide_mm_s)

    @property
    def _stride(self) -> int:
        return 5 if self.max_slide_mm_s < np.inf else 1

    def max_rows(self, group_size: int) -> int:
        return self._stride * group_size

    def row_name(self, index: int, point_names: tuple) -> str:
        """"<name>:<point>" for a point's barrier row, "<name>:<point> slide" for its slide rows."""
        i, r = divmod(index, self._stride)
        if i < len(point_names):
            return f"{self.name}:{point_names[i]}" + (" slide" if r else "")
        return self.name

    def fault_reason(self, code: int) -> str:
        return "model returned non-finite distance or gradient"
