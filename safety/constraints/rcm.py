"""Remote centre of motion: the shaft pivots about the trocar.

The shaft's material point at the trocar C (group "trocar": one point, the body I's
x axis along the shaft) may move only along the shaft: its velocity along the shaft's
two lateral axes (columns 1 and 2 of R_WI) is zero, and the lateral error e (mm) of the
shaft from C decays as de/dt = -gain e (drift correction):

    n_a . J_C qdot = gain e_a,   a = 1, 2,

where e_a is the error predicted for the end of the motion the actuator still carries
out if every command from this step on is zero: the rows of `pending`, D = sum_r
pending_r (rad) (safety.actuator.ActuatorModel.pending_rows; none for the ideal
actuator). The correction acts on that error, not on today's: a robot that applies a
command late (delay, lag, an acceleration limit) would otherwise receive the same
correction again at every step until the first one arrives, overshoot, and swing about
the trocar with a growing error, until the correction it needs exceeds what the speed
limits allow and the QP has no solution. Correcting the predicted error (a Smith
predictor on the drift loop) makes every step's correction act once: e decays by
(1 - gain dt) per step as with the ideal actuator.

The prediction is the mean of two: the first order, n_a . (p_WC - p_WI - J_C D), and the
lateral offset of the trocar from the shaft at the end pose, the kinematics at q + D
(R_WI_end, p_WI_end; the loop's compiled step evaluates them there), projected on the
present lateral axes. The actuator brakes along a straight line in joint space (it keeps
the direction of its velocity: safety.actuator), and a straight joint path leaves the
pivot by the kinematics' second order, ~ s^2 delta over the fraction s of the path. The
first order alone misses it: an acceleration-limited robot (1000 deg/s^2) that a 3 rad/s
roll command took to 1.6-2.9 rad/s on joints 1, 4 and 6 brakes over ~0.2 s and 0.2-0.3
rad, and its pivot drifted 1.97 mm from the trocar while the first-order prediction saw
0.2 mm (the pointed eye, every robot error at once, quadric boundary, seed 4242).
Correcting the end pose's offset alone holds the end and leaves the shaft off the trocar
by the whole second order while it moves (112 um on that campaign); the mean holds the
present offset near -delta / 2 and the end near +delta / 2, the smallest largest offset
over the path (e0 + s^2 delta over s in [0, 1] is smallest at e0 = -delta / 2).

Planned stops. The filler refuses the step with the reason "actuator cannot hold the
trocar" (zero command: the fastest braking the actuator allows) when the pending motion
carries the shaft further from the trocar (by more than GROWTH_TOL_MM: a lag's tail never
reaches zero velocity, and a stop on its last micrometres would hold a robot at rest for
hundreds of steps) to
- a first-order offset whose correction at the gain would exceed `max_correction_mm_s`,
  the speed the tip speed limit allows in every direction (safety.filter.rcm_constraint:
  TipSpeedLimit.every_direction_mm_s, 17.4 mm/s at the default 20 mm/s limit; 0.087 mm
  of error at 200/s): a robot that cannot pivot about the tip (a joint at its position
  limit) corrects the trocar by moving the whole shaft, tip included, and a growing error
  whose correction the tip could not follow in every direction leaves the QP no velocity
  a step later (measured: a 20 ms lag on the staphyloma, 19.8 mm/s of correction, the
  third joint 0.34 rad/s from its limit bound); or
- an offset at the end pose BRAKING_FACTOR times that (0.174 mm): a stop then leaves
  the pivot at most that far off. At the correction's own threshold this rule stops
  ordinary motion: the spiral that builds the model moves the wrist at 1.5 rad/s in its
  first second, whose braking ends 70-90 um off, and under the acceleration limit the
  build spent 92,000 of its 107,000 steps in such stops.
A robot at rest with an error keeps correcting it at the gain, as with the ideal
actuator, which never stops here: its prediction is today's error. (A bound on the
correction's speed at the threshold does worse: an acceleration-limited robot then
carries a 0.1-0.2 mm error for tens of steps at its joint speed limits until the QP has
no solution; measured on the fault matrix.) Measured with both rules and the mean
(pointed eye, every robot error at once, quadric boundary, seed 4242, 100 scenarios):
largest trocar error 89 um, against 1,969 um with the first order alone.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from safety.constraints.base import Constraint, as_params, check_finite_positive
from safety.constraints.tip_speed import TipSpeedLimit

CANNOT_HOLD = 1  # the filler's fault code
GROWTH_TOL_MM = 1e-3  # the pending motion's growth of the offset that counts (module docstring: planned stops)
BRAKING_FACTOR = 2.0  # the end pose's offset that stops, in units of the correction's max / gain


@njit(cache=True)
def displaced(q, pending):
    """q (n,) rad plus the sum of the rows of `pending` (r, n) rad, row by row: the joint
    angles once the actuator has carried out its pending motion (the RCM's end pose is the
    kinematics there, in the loop's compiled step and in the Python inputs alike); q itself
    when a row is not finite (the barriers fault on it)."""
    out = q.copy()
    if not np.all(np.isfinite(pending)):
        return out
    for k in range(pending.shape[0]):
        for j in range(q.shape[0]):
            out[j] += pending[k, j]
    return out


@njit(cache=True)
def fill_rcm(sp, J, start, R_WI, p_WI, R_WI_end, p_WI_end, pending, A, b, p):
    """sp = [p_WC (3) mm, gain 1/s, max correction mm/s]: two rows A qdot = b for the point
    J[start], their correction the mean of the trocar's lateral offset from the shaft
    predicted to first order (J[start] times the `pending` rows' sum, rad) and at the end
    pose (R_WI_end, p_WI_end), along the present lateral axes; both rows written, then
    -CANNOT_HOLD on either planned stop (module docstring)."""
    n = J.shape[2]
    c0, c1, c2 = sp[0] - p_WI[0], sp[1] - p_WI[1], sp[2] - p_WI[2]
    now = 0.0  # the present error's squared length
    for a in range(2):
        now += (R_WI[0, a + 1] * c0 + R_WI[1, a + 1] * c1 + R_WI[2, a + 1] * c2) ** 2
    for k in range(pending.shape[0]):  # first order: the trocar's material point moved by J D
        for j in range(n):
            c0 -= J[start, 0, j] * pending[k, j]
            c1 -= J[start, 1, j] * pending[k, j]
            c2 -= J[start, 2, j] * pending[k, j]
    d0, d1, d2 = sp[0] - p_WI_end[0], sp[1] - p_WI_end[1], sp[2] - p_WI_end[2]
    along = R_WI_end[0, 0] * d0 + R_WI_end[1, 0] * d1 + R_WI_end[2, 0] * d2
    d0, d1, d2 = d0 - along * R_WI_end[0, 0], d1 - along * R_WI_end[1, 0], d2 - along * R_WI_end[2, 0]
    first = 0.0
    for a in range(2):
        e_first = R_WI[0, a + 1] * c0 + R_WI[1, a + 1] * c1 + R_WI[2, a + 1] * c2
        e_end = R_WI[0, a + 1] * d0 + R_WI[1, a + 1] * d1 + R_WI[2, a + 1] * d2
        e = 0.5 * (e_first + e_end)
        first += e_first * e_first
        b[p] = sp[3] * e
        for j in range(n):
            A[p, j] = (R_WI[0, a + 1] * J[start, 0, j] + R_WI[1, a + 1] * J[start, 1, j]
                       + R_WI[2, a + 1] * J[start, 2, j])
        p += 1
    now, first, end = np.sqrt(now), np.sqrt(first), np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    if first > now + GROWTH_TOL_MM and sp[3] * first > sp[4]:
        return -CANNOT_HOLD
    if end > now + GROWTH_TOL_MM and sp[3] * end > BRAKING_FACTOR * sp[4]:
        return -CANNOT_HOLD
    return p


@dataclass(frozen=True, eq=False)
class RcmEquality(Constraint):
    """The shaft passes through the trocar p_WC (3,) mm in W, drift corrected at gain_per_s;
    a growing error whose correction is faster than max_correction_mm_s (mm/s; the default:
    what the default tip speed limit allows in every direction) stops the robot (module
    docstring)."""

    p_WC: np.ndarray
    gain_per_s: float
    group: str = "trocar"
    name: str = "rcm"
    max_correction_mm_s: float = TipSpeedLimit().every_direction_mm_s

    kind = "equality"
    filler = staticmethod(fill_rcm)
    intervenes = False
    drift_correction = True  # b is the correction; a step with no other solution eases it (safety.stack)

    def __post_init__(self):
        check_finite_positive("RcmEquality", gain_per_s=self.gain_per_s, max_correction_mm_s=self.max_correction_mm_s)
        if np.shape(self.p_WC) != (3,) or not np.all(np.isfinite(self.p_WC)):
            raise ValueError(f"RcmEquality.p_WC must be 3 finite mm, got {self.p_WC}")

    def params(self) -> np.ndarray:
        return as_params(self.p_WC, self.gain_per_s, self.max_correction_mm_s)

    def max_rows(self, group_size: int) -> int:
        return 2

    def fault_reason(self, code: int) -> str:
        if code == CANNOT_HOLD:
            return "actuator cannot hold the trocar"
        return super().fault_reason(code)
