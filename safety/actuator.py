"""The robot's actuator as the filter is told it: pure delay, first-order velocity lag,
per-joint acceleration limits (s, rad/s, rad/s^2).

The controller applies, at each control step k, the velocity

    target_k = the command of `delay_steps` steps earlier (the newest one without delay)
    v_k      = v_{k-1} + alpha (target_k - v_{k-1}),  alpha = 1 - exp(-dt / lag_s)
    v_k      = v_{k-1} + s (v_k - v_{k-1}),  s = min(1, accel dt / max_j |v_kj - v_{k-1,j}|)

and the joints move by dt v_k in that step. The acceleration limit scales the change of
all joints alike, the fastest-changing joint at the limit (the Meca500 moves its joints
in velocity mode so that they start and stop together: the joint-space direction, and
with it the instrument's pivot about the trocar, is kept). With no delay, no lag and no limit this is
the ideal loop: each command applied over the next control period.

`pending_rows` gives the filter what the actuator still carries out if every command
from this step on is zero, as joint displacements (rad) whose contributions to the joint
path each grow monotonically from 0 to the full row: one row per queued command, the
step it is the target (dt x the velocity the actuator reaches then, by the rule above:
exact, the acceleration limit included), and a last row for the braking from the
velocity v the queue leaves, with target zero. That braking keeps the direction of v
(the lag's step and the limit's scaling are both along -v), so its displacement is a
growing multiple of v, at most v (dt (1 - alpha) / alpha) for the lag and, with the
limit, v (max_j |v_j| / (2 accel) + dt / 2) more (the fastest joint brakes at the limit,
the discrete ramp adding at most half a step; a lag slowed by the limit covers at most
v tau + v max|v| / (2 accel)). So a point's motion towards a wall over the whole
braking is at most the sum of the rows' inward parts: the bound the actuator-aware
barrier (safety.constraints.actuated_barrier) keeps in its margin. Counting each queued
command at its own full displacement (dt x command, a linear lag's unit gain) is not a
bound under the limit: a queue of fast commands (a 3 rad/s wrist roll) raises the
velocity the robot then has to brake from, and the limit, shared by all joints, slows
every joint's braking with the roll's (measured: 8.2 mrad along a joint direction where
that count gave 3.6).

Meca500 (Mecademic programming manual): joint speeds up to 150/150/180/300/300/500 deg/s
(R3); in velocity mode (MoveJointsVel) the robot stops by itself after SetVelTimeout
(default 0.050 s) without a new command; the joint acceleration is a percentage
(SetJointAcc) of a maximum the manual does not state in deg/s^2. The defaults here are
the ideal actuator; the fault campaigns' values are assumptions stated there
(eval.experiments.faults).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit


@dataclass(frozen=True)
class ActuatorModel:
    """delay_s (>= 0, applied in whole control periods, rounded to the nearest), lag_s
    (first-order time constant, >= 0), accel_limit_rad_s2 (per joint, > 0; inf: none)."""

    delay_s: float = 0.0
    lag_s: float = 0.0
    accel_limit_rad_s2: float = np.inf

    def __post_init__(self):
        for name in ("delay_s", "lag_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and 0.0 <= v <= 1.0):
                raise ValueError(f"ActuatorModel.{name} must be in [0, 1] s, got {v}")
        a = self.accel_limit_rad_s2
        if not (a == a and a > 0):
            raise ValueError(f"ActuatorModel.accel_limit_rad_s2 must be > 0 rad/s^2 (inf: none), got {a}")

    @property
    def ideal(self) -> bool:
        return self.delay_s == 0.0 and self.lag_s == 0.0 and self.accel_limit_rad_s2 == np.inf

    def delay_steps(self, dt: float) -> int:
        """The delay in whole control periods of dt s."""
        return int(round(self.delay_s / dt))

    def alpha(self, dt: float) -> float:
        """The lag's per-step gain (1: no lag)."""
        return 1.0 if self.lag_s == 0.0 else float(-np.expm1(-dt / self.lag_s))

    def horizon_s(self, dt: float) -> float:
        """How long a command takes to act: the delay plus the lag's time constant (s)."""
        return self.delay_steps(dt) * dt + self.lag_s

    def advance(self, v: np.ndarray, target: np.ndarray, dt: float) -> np.ndarray:
        """The velocity (n,) rad/s applied this step, from the last one v and the target."""
        out = np.empty(len(v))
        advance_into(np.asarray(v, dtype=float), np.asarray(target, dtype=float), self.alpha(dt),
                     self.accel_limit_rad_s2 * dt, out)
        return out

    def pending_rows(self, v: np.ndarray, queued: np.ndarray, dt: float) -> np.ndarray:
        """(len(queued) + 1, n) rad: the joint displacements still to come from the applied
        velocity v (n,) rad/s and the queued commands (r, n) rad/s, oldest first (the one
        the actuator takes next first), if every later command is zero (module docstring)."""
        queued = np.asarray(queued, dtype=float).reshape(-1, len(v))
        rows = np.empty((len(queued) + 1, len(v)))
        braking_rows(np.asarray(v, dtype=float), queued, dt, self.alpha(dt), self.accel_limit_rad_s2, rows)
        return rows


@njit(cache=True)
def advance_into(v, target, alpha, accel_dt, out):
    """out = the velocity applied after v towards target (module docstring's rule): the
    lag's step alpha (target - v), scaled down so that no joint changes by more than
    accel_dt (rad/s; inf: no limit)."""
    largest = 0.0
    for j in range(len(v)):
        largest = max(largest, abs(alpha * (target[j] - v[j])))
    s = 1.0 if largest <= accel_dt else accel_dt / largest
    for j in range(len(v)):
        out[j] = v[j] + s * alpha * (target[j] - v[j])


@njit(cache=True)
def braking_rows(v, queued, dt, alpha, accel, rows):
    """rows[k] = dt x the velocity of the step whose target is queued[k]; rows[-1] the
    braking from the last of them with target zero (ActuatorModel.pending_rows)."""
    n = len(v)
    cur, nxt = v.copy(), np.empty(n)
    for k in range(queued.shape[0]):
        advance_into(cur, queued[k], alpha, accel * dt, nxt)
        for j in range(n):
            cur[j] = nxt[j]
            rows[k, j] = dt * nxt[j]
    tail = dt * (1.0 - alpha) / alpha
    if accel != np.inf:
        fastest = 0.0
        for j in range(n):
            fastest = max(fastest, abs(cur[j]))
        tail += fastest / (2.0 * accel) + 0.5 * dt
    for j in range(n):
        rows[queued.shape[0], j] = cur[j] * tail
