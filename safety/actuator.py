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
from this step on is zero: one joint displacement (rad) per source, the lag state's
(v dt (1 - alpha) / alpha, grown by v max_j |v_j| / (2 accel) for the braking the
acceleration limit allows) and each command still queued (dt x command; a first-order lag has unit
gain, so each queued command moves the joints by exactly that much in all). Each row's
contribution to the joint path grows monotonically from 0 to the full row (the lag's
step and impulse responses do not change sign), so a point's motion towards a wall over
the whole braking is at most the sum of the rows' inward parts: the bound the
actuator-aware barrier (safety.constraints.actuated_barrier) keeps in its margin. The
acceleration limit makes the actuator non-linear: its row is a bound for braking from v
(a lag slowed by the limit covers at most v tau + v max|v| / (2 accel)), and queued
commands are counted at their full displacement.

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
        step = self.alpha(dt) * (target - v)
        if self.accel_limit_rad_s2 != np.inf:
            largest = float(np.max(np.abs(step)))
            lim = self.accel_limit_rad_s2 * dt
            if largest > lim:
                step = step * (lim / largest)
        return v + step

    def pending_rows(self, v: np.ndarray, queued: np.ndarray, dt: float) -> np.ndarray:
        """(1 + len(queued), n) rad: the joint displacements still to come from the lag
        state v (n,) rad/s and the queued commands (r, n) rad/s, oldest first, if every
        later command is zero (module docstring)."""
        a = self.alpha(dt)
        rows = np.empty((1 + len(queued), len(v)))
        rows[0] = v * (dt * (1.0 - a) / a)
        if self.accel_limit_rad_s2 != np.inf:
            rows[0] += v * (np.max(np.abs(v)) / (2.0 * self.accel_limit_rad_s2))
        rows[1:] = dt * np.asarray(queued)
        return rows
