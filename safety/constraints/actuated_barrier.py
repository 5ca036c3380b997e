"""Actuator-aware point barrier: the point barrier's rule on the clearance the point
keeps once the actuator has carried out what it still carries.

The filter is told the actuator (safety.actuator.ActuatorModel: delay, first-order lag,
acceleration limit) and, each step, what it still carries out if every command from
this step on is zero: the rows of `pending` (r, n) rad, one per queued command's step and
one for the braking after them (safety.actuator.ActuatorModel.pending_rows). The robot
does not stop when the filter commands zero; it stops after those displacements.

Safety argument. For a point p (Jacobian J_p, field h with unit gradient g) the braking
still to come moves p by J_p (sum_r w_r(t) pending_r), each weight w_r(t) rising
monotonically from 0 to 1 (safety.actuator). So at any time during the braking, the
point's approach to the wall along g is at most

    b = sum_r max(0, -g . J_p pending_r)          (first order)
      + 1/2 sum_ij D_i D_j |J_p[:, max(i, j)]|     (the kinematics' second order)
      + |d|^2 / (2 R)                              (the field's curvature)

with D_j = sum_r |pending_rj| the joints' braking travel (rad), |d| <= sum_r |J_p
pending_r| + the second-order term the point's braking travel, and R
(`curvature_radius_mm`) a lower bound on the retina's radius of curvature (a distance
field inside a surface of radius >= R departs from its tangent plane by at most
|d|^2 / (2 R) over |d|). The second order: for revolute joints the second derivative of
p along joints i <= j is a_i x (a_j x (p - o_j)), no longer than column j of J_p, so p
leaves its tangent J_p D by at most the term above (a fast wrist roll during a 5 ms delay
turns the instrument by tens of mrad: tens of um at the tip); higher orders are left out. The
barrier keeps the PREDICTED clearance h^ = h - b above h_min, with the point barrier's
row (safety.constraints.point_barrier) on h^: -g . J_p qdot <= gain (h^ - h_min). The
step's command qdot joins the queue; over one step it adds at most dt max(0, -g . J_p
qdot) to b, while the queued displacement it executes leaves h^ unchanged (inward: h
and b fall alike) or raises it (outward). So h^_{k+1} - h_min >= (1 - gain dt)
(h^_k - h_min): once h^ >= h_min, it stays there, and since the point's worst clearance
over any braking is at least h^, the point keeps h_min however the command changes,
including a stop. With an ideal actuator (no rows) h^ = h: the point barrier itself.
Linearisation (J_p over the braking travel, sub-millimetre) and, under the acceleration
limit, a new command's effect on the braking after it (the limit is shared by all joints:
it is not dt qdot) are not covered by the argument; each step's pending rows are (the
queue's steps exact, the braking bounded), so a step that finds its prediction short is
a planned stop (below); the campaigns measure the rest.

Planned stop. A point whose present clearance is within `stop_tolerance_mm` of h_min but
whose predicted clearance is not (h >= h_min - tol > h^: the actuator's motion, not the
model, takes it past the margin) refuses the step with the reason "actuator cannot brake
before the boundary": zero command, the fastest braking the actuator allows, rather than
a QP that finds no velocity a few steps later. It holds until the queue drains.

The clearance the barrier reports (`point_h`) is the present one, h, and so is the bound
on the true clearance it assumes (`point_bound`: h - k sigma - calibration).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from safety.constraints.base import as_params, check_finite_positive
from safety.constraints.point_barrier import NON_FINITE_FIELD, PointBarrier, fill_point_barrier

CANNOT_BRAKE = 2  # the filler's fault code (NON_FINITE_FIELD = 1; non-finite pending rows: the step's input fault)


@njit(cache=True)
def braking_margins(side, P, J, start, stop, fh, fg, pending, inv_2r, revolute, out):
    """out[i] = b of the group's point i (module docstring), mm (the second-order term only
    with `revolute` joints); NaN where fh or fg is not finite."""
    n = J.shape[2]
    D = np.zeros(n)
    for k in range(pending.shape[0]):
        for j in range(n):
            D[j] += abs(pending[k, j])
    for i in range(stop - start):
        r = start + i
        second = 0.0
        for a in range(n):
            for c in range(n):
                col = max(a, c)
                second += D[a] * D[c] * np.sqrt(J[r, 0, col] ** 2 + J[r, 1, col] ** 2 + J[r, 2, col] ** 2)
        second *= 0.5 * revolute
        inward, travel = second, second
        for k in range(pending.shape[0]):
            d0, d1, d2 = 0.0, 0.0, 0.0
            for j in range(n):
                d0 += J[r, 0, j] * pending[k, j]
                d1 += J[r, 1, j] * pending[k, j]
                d2 += J[r, 2, j] * pending[k, j]
            along = side * (fg[i, 0] * d0 + fg[i, 1] * d1 + fg[i, 2] * d2)
            if along < 0.0:
                inward -= along
            travel += np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        out[i] = inward + travel * travel * inv_2r
    return out


@njit(cache=True)
def fill_actuated_barrier(sp, P, J, start, stop, fh, fg, fu, pending, G, h, ids, m, id0, point_h, point_bound):
    """sp = [len(base), the PointBarrier's params (base), 1 / (2 R) 1/mm, stop tolerance mm,
    revolute joints 1/0];
    the point barrier's rows on the predicted clearance, or -CANNOT_BRAKE (module docstring)."""
    nb = int(sp[0])
    base = sp[1:1 + nb]
    side, d_safe, k_sigma, calibration = base[0], base[1], base[2], base[7]
    inv_2r, tol, revolute = sp[1 + nb], sp[2 + nb], sp[3 + nb]
    k = stop - start
    b = braking_margins(side, P, J, start, stop, fh, fg, pending, inv_2r, revolute, np.empty(k))
    predicted = np.empty(k)
    for i in range(k):
        if fh[i] == np.inf and side > 0.0:  # no boundary at this point
            predicted[i] = fh[i]
            continue
        if not (np.isfinite(fh[i]) and np.isfinite(b[i]) and np.isfinite(fu[i])):
            return -NON_FINITE_FIELD
        h_min = d_safe + k_sigma * fu[i] + calibration
        present = side * fh[i]
        if b[i] > 0.0 and present >= h_min - tol and present - b[i] < h_min - tol:
            return -CANNOT_BRAKE
        predicted[i] = side * (present - b[i])
    m_out = fill_point_barrier(base, P, J, start, stop, predicted, fg, fu, G, h, ids, m, id0, point_h, point_bound)
    if m_out >= 0:
        for i in range(k):
            if point_h[start + i] != np.inf:  # the present clearance and bound: the predicted ones moved back by b
                point_bound[start + i] += side * fh[i] - point_h[start + i]
                point_h[start + i] = side * fh[i]
    return m_out


@dataclass(frozen=True)
class ActuatedPointBarrier(PointBarrier):
    """A PointBarrier on the predicted clearance (module docstring): `curvature_radius_mm`
    a lower bound on the field's radius of curvature, `stop_tolerance_mm` how far past
    h_min the actuator may be predicted to carry a point before the filter stops,
    `revolute_joints` the robot's joints turn (the kinematics' second-order term; False
    for joints that translate the points, whose kinematics are linear)."""

    curvature_radius_mm: float = 5.0
    stop_tolerance_mm: float = 0.05
    revolute_joints: bool = True

    filler = staticmethod(fill_actuated_barrier)

    def __post_init__(self):
        super().__post_init__()
        check_finite_positive(type(self).__name__, curvature_radius_mm=self.curvature_radius_mm,
                              stop_tolerance_mm=self.stop_tolerance_mm)

    @classmethod
    def of(cls, barrier: PointBarrier, **kwargs) -> "ActuatedPointBarrier":
        """The actuator-aware version of `barrier` (its fields kept)."""
        fields = {f: getattr(barrier, f) for f in PointBarrier.__dataclass_fields__}
        return cls(**fields, **kwargs)

    def params(self) -> np.ndarray:
        base = super().params()
        return as_params(len(base), base, 0.5 / self.curvature_radius_mm, self.stop_tolerance_mm,
                         float(self.revolute_joints))

    def fault_reason(self, code: int) -> str:
        if code == CANNOT_BRAKE:
            return "actuator cannot brake before the boundary"
        return super().fault_reason(code)


__all__ = ["ActuatedPointBarrier", "braking_margins", "fill_actuated_barrier"]


def actuator_aware(constraints) -> list:
    """The stack `constraints` for an actuator that is not ideal: every PointBarrier made an
    ActuatedPointBarrier (its fields kept, the defaults above), the rest as they are."""
    return [ActuatedPointBarrier.of(c) if type(c) is PointBarrier else c for c in constraints]
