"""Command sources for the closed loop: what the surgeon (or a planner) asks of the tip.

A command source is called once per control step, in time order, as
`source(t_s, p_WT, q) -> (v_W (3,) mm/s, roll_rate rad/s)` with the current tip position
p_WT (mm, W) and joint angles q (rad). The safety filter decides what is actually done.

- `TipPathCommand`: a time-parameterised tip path (planned paths): feed-forward velocity
  plus position feedback.
- `PacedTipPath`: the same path on its own clock, which slows while the tip lags behind
  its reference (the model-building spiral on a robot with a declared actuator lag,
  delay or acceleration limit): a robot that cannot keep up scans the whole path late
  rather than cut it short.
- `VelocityReplayCommand`: recorded tip velocities (and roll rates), zero-order hold.
- `AdversarialCommand`: a seeded adversary that pushes toward and along the retina at up
  to the speed limit, moves laterally with roll so the cutter port faces the retina, and
  pushes toward the lens.
"""
from __future__ import annotations

import math
from bisect import bisect_right

import numpy as np

from models.shapes.validation import as_points, as_positive, as_vector3

ADVERSARY_MODES = ("push", "along", "port_side", "lens", "random")
# how often each mode is drawn: mostly attacks on the retina, some on the lens
ADVERSARY_WEIGHTS = {"push": 0.4, "along": 0.15, "port_side": 0.2, "lens": 0.1, "random": 0.15}


class TipPathCommand:
    """Follow tip positions P_WT (M, 3) mm at times_s (M,) s (strictly increasing):
    v = (P[k+1] - P[k]) / (t[k+1] - t[k]) on the current segment plus
    gain_per_s x (p_des(t) - p_WT), the feedback capped at `max_feedback_mm_s` (a tip held
    back by the boundary catches up at a bounded speed, never with an absurd command);
    holds the last point after the end. `roll_rad` (M,) optional roll angles about the
    shaft, commanded as their rate (feed-forward only)."""

    def __init__(self, times_s, P_WT, roll_rad=None, gain_per_s: float = 20.0, max_feedback_mm_s: float = 10.0):
        t = np.asarray(times_s, dtype=float)
        P = as_points(P_WT, "P_WT")
        if t.ndim != 1 or len(t) != len(P) or len(t) < 2:
            raise ValueError(f"times_s must be (M,) with M = len(P_WT) >= 2, got {t.shape} for {len(P)} points")
        if not (np.all(np.isfinite(t)) and np.all(np.diff(t) > 0)):
            raise ValueError("times_s must be finite and strictly increasing (s)")
        self.times_s, self.P_WT = t, P
        self.gain_per_s = as_positive(gain_per_s, "gain_per_s")
        self.max_feedback_mm_s = as_positive(max_feedback_mm_s, "max_feedback_mm_s")
        V = np.diff(P, axis=0) / np.diff(t)[:, None]
        if roll_rad is None:
            roll_rate = np.zeros(len(t) - 1)
        else:
            roll = np.asarray(roll_rad, dtype=float)
            if roll.shape != t.shape or not np.all(np.isfinite(roll)):
                raise ValueError(f"roll_rad must be finite with the shape of times_s {t.shape}, got {roll.shape}")
            roll_rate = np.diff(roll) / np.diff(t)
        # as Python floats: one control step's arithmetic is scalar
        self._t, self._P = t.tolist(), [tuple(p) for p in P.tolist()]
        self._Vl, self._roll_l = [tuple(v) for v in V.tolist()], roll_rate.tolist()

    @property
    def duration_s(self) -> float:
        return float(self.times_s[-1] - self.times_s[0])

    def path_fraction(self, t_s: float) -> float:
        """Fraction (0-1) of the path's duration done at call time t_s (s)."""
        return (min(max(float(t_s), self._t[0]), self._t[-1]) - self._t[0]) / (self._t[-1] - self._t[0])

    def reference(self, t_s: float) -> np.ndarray:
        """p_des (3,) mm at t_s (clamped to the path's ends)."""
        return np.array(self._reference(float(t_s), self._segment(t_s)))

    def _segment(self, t_s: float) -> int:
        """Index k of the segment [t_k, t_k+1) holding t_s: -1 before the path, M - 1 after."""
        return bisect_right(self._t, t_s) - 1

    def _reference(self, t_s: float, k: int) -> tuple[float, float, float]:
        """p_des (mm) at t_s on segment k: P_k + V_k (t_s - t_k), the path's ends outside."""
        if k < 0:
            return self._P[0]
        if k >= len(self._Vl):
            return self._P[-1]
        (x, y, z), (vx, vy, vz), dt = self._P[k], self._Vl[k], t_s - self._t[k]
        return x + vx * dt, y + vy * dt, z + vz * dt

    def __call__(self, t_s: float, p_WT, q) -> tuple[np.ndarray, float]:
        """(v_W (3,) mm/s, roll rate rad/s) at t_s for the tip at p_WT (3,) mm in W: scalar
        arithmetic on the path's precomputed segments (called at the control rate)."""
        return self._command(float(t_s), p_WT, 1.0)

    def _command(self, t_s: float, p_WT, pace: float) -> tuple[np.ndarray, float]:
        """The command at path time t_s with the feed-forward (and roll rate) times `pace`."""
        k = self._segment(t_s)
        inside = 0 <= k < len(self._Vl)
        vx, vy, vz = self._Vl[k] if inside else (0.0, 0.0, 0.0)
        rx, ry, rz = self._reference(t_s, k)
        px, py, pz = p_WT
        g = self.gain_per_s
        fx, fy, fz = g * (rx - px), g * (ry - py), g * (rz - pz)
        n = math.sqrt(fx * fx + fy * fy + fz * fz)
        if n > self.max_feedback_mm_s:
            s = self.max_feedback_mm_s / n
            fx, fy, fz = fx * s, fy * s, fz * s
        return np.array((pace * vx + fx, pace * vy + fy, pace * vz + fz)), (pace * self._roll_l[k] if inside else 0.0)


# The paced path's clock (PacedTipPath): full pace while the tip is within PACE_FREE_MM of its reference (a
# first-order lag of 20 ms trails a 15 mm/s reference by 0.3 mm: its ordinary tracking leaves the pace alone), the
# slowest pace PACE_FLOOR from PACE_HOLD_MM behind, linear between. The floor is not zero, so that a tip held by
# the boundary itself (a model that places the retina across the path) cannot stop the scan: the path then takes
# at most 1 / PACE_FLOOR times its own duration.
PACE_FREE_MM = 0.5
PACE_HOLD_MM = 2.0
PACE_FLOOR = 0.25


class PacedTipPath(TipPathCommand):
    """A TipPathCommand on its own clock: `path_time_s` starts at the path's first time at
    the first call and advances by pace x (the time since the previous call), the pace 1
    while the tip is within `free_mm` of the reference at path_time_s, `floor` from `hold_mm`
    on, linear between; the command is the path's feed-forward (and roll rate) times the
    pace plus the capped position feedback to that reference. `finished` once the path's
    clock has reached its end and the tip has come within `free_mm` of the last point, or
    has been pulled toward it for `settle_s` (s; default the time the capped feedback takes
    over 2 hold_mm): the closed loop then ends the run (ClosedLoop.run_segments).
    `path_fraction(t_s)`: the fraction of the path's duration done at call time t_s."""

    def __init__(self, times_s, P_WT, roll_rad=None, gain_per_s: float = 20.0, max_feedback_mm_s: float = 10.0,
                 free_mm: float = PACE_FREE_MM, hold_mm: float = PACE_HOLD_MM, floor: float = PACE_FLOOR,
                 settle_s: float | None = None):
        super().__init__(times_s, P_WT, roll_rad, gain_per_s, max_feedback_mm_s)
        self.free_mm = float(free_mm)
        self.hold_mm = float(hold_mm)
        self.floor = float(floor)
        if not (np.isfinite(self.free_mm) and 0 <= self.free_mm < self.hold_mm < np.inf):
            raise ValueError(f"free_mm and hold_mm must satisfy 0 <= free_mm < hold_mm (mm), got {free_mm}, {hold_mm}")
        if not (0 < self.floor <= 1):
            raise ValueError(f"floor must be in (0, 1], got {floor}")
        self.settle_s = 2.0 * self.hold_mm / self.max_feedback_mm_s if settle_s is None else float(settle_s)
        if not self.settle_s >= 0:
            raise ValueError(f"settle_s must be >= 0 s, got {settle_s}")
        self.path_time_s = self._t[0]
        self.finished = False
        self._t_last: float | None = None
        self._t_end: float | None = None  # call time at which the clock reached the path's end
        self._calls_t: list[float] = []
        self._calls_path: list[float] = []

    def path_fraction(self, t_s: float) -> float:
        """Fraction (0-1) of the path's duration done by call time t_s (s)."""
        if not self._calls_t:
            return 0.0
        tau = float(np.interp(t_s, self._calls_t, self._calls_path))
        return (tau - self._t[0]) / (self._t[-1] - self._t[0])

    def pace(self, lag_mm: float) -> float:
        """The clock's rate (floor-1) for a tip `lag_mm` from its reference."""
        x = min(max((lag_mm - self.free_mm) / (self.hold_mm - self.free_mm), 0.0), 1.0)
        return 1.0 - (1.0 - self.floor) * x

    def __call__(self, t_s: float, p_WT, q) -> tuple[np.ndarray, float]:
        t_s = float(t_s)
        tau = self.path_time_s
        rx, ry, rz = self._reference(tau, self._segment(tau))
        px, py, pz = p_WT
        lag_mm = math.sqrt((rx - px) ** 2 + (ry - py) ** 2 + (rz - pz) ** 2)
        rate = self.pace(lag_mm)
        if self._t_end is not None:
            self.finished = lag_mm <= self.free_mm or t_s - self._t_end >= self.settle_s
        elif self._t_last is not None and t_s > self._t_last:
            tau = self.path_time_s = min(tau + rate * (t_s - self._t_last), self._t[-1])
            if tau >= self._t[-1]:
                self._t_end = t_s
        self._t_last = t_s
        self._calls_t.append(t_s)
        self._calls_path.append(tau)
        return self._command(tau, p_WT, rate)  # the feed-forward at the clock's pace


class VelocityReplayCommand:
    """Recorded tip velocities V_W (M, 3) mm/s (and roll rates (M,) rad/s) from times_s
    (M,) s on, held until the next sample; zero after the last sample + its period (a
    single sample is held to the end of the run)."""

    def __init__(self, times_s, V_W, roll_rate=None):
        t = np.asarray(times_s, dtype=float)
        V = np.asarray(V_W, dtype=float)
        if t.ndim != 1 or len(t) < 1 or V.shape != (len(t), 3):
            raise ValueError(f"times_s (M,) and V_W (M, 3) mm/s must match, got {t.shape} and {V.shape}")
        if not np.all(np.diff(t) > 0):
            raise ValueError("times_s must be strictly increasing (s)")
        self.times_s, self.V_W = t, V  # non-finite velocities are passed on: the filter stops on them
        self.roll_rate = np.zeros(len(t)) if roll_rate is None else np.asarray(roll_rate, dtype=float).reshape(len(t))
        self._end = t[-1] + np.median(np.diff(t)) if len(t) > 1 else np.inf  # one sample: held to the end

    def __call__(self, t_s: float, p_WT, q) -> tuple[np.ndarray, float]:
        k = int(np.searchsorted(self.times_s, t_s, side="right")) - 1
        if k < 0 or t_s >= self._end:
            return np.zeros(3), 0.0
        return self.V_W[k].copy(), float(self.roll_rate[k])


class AdversarialCommand:
    """A seeded adversary: segments of `segment_s` (uniform in the range, s), each of one
    mode drawn from `modes` (weights ADVERSARY_WEIGHTS; the first segment always pushes
    toward the retina) with a speed uniform in [0.5, 1] x `max_speed_mm_s`:

    - "push": straight toward the retina (away from the eye centre p_WE_center), +-15 deg;
    - "along": tangential to the retina, with a 20 % push outward;
    - "port_side": a lateral push plus a roll of up to `max_roll_rate` rad/s (turns the
      cutter port, 0.25 mm off the axis, toward the retina);
    - "lens": toward the lens centre p_W_lens;
    - "random": any direction.
    Directions are drawn at the start of a segment from the tip's position then, and held.
    """

    def __init__(self, seed: int, p_WE_center, p_W_lens, max_speed_mm_s: float = 20.0,
                 segment_s=(0.05, 0.2), modes=ADVERSARY_MODES, max_roll_rate: float = 3.0):
        self._rng = np.random.default_rng(seed)
        self.p_WE_center = as_vector3(p_WE_center, "p_WE_center")
        self.p_W_lens = as_vector3(p_W_lens, "p_W_lens")
        self.max_speed_mm_s = as_positive(max_speed_mm_s, "max_speed_mm_s")
        self.max_roll_rate = float(max_roll_rate)
        if not (np.isfinite(self.max_roll_rate) and self.max_roll_rate >= 0):
            raise ValueError(f"max_roll_rate must be >= 0 rad/s, got {max_roll_rate}")
        lo, hi = segment_s
        if not (0 < lo <= hi):
            raise ValueError(f"segment_s must be (lo, hi) s with 0 < lo <= hi, got {segment_s}")
        bad = [m for m in modes if m not in ADVERSARY_MODES]
        if bad or not modes:
            raise ValueError(f"modes must be a non-empty subset of {ADVERSARY_MODES}, got {modes}")
        self.segment_s, self.modes = (float(lo), float(hi)), tuple(modes)
        self._until = -np.inf
        self._v, self._roll = np.zeros(3), 0.0
        self.mode_log: list[tuple[float, str]] = []

    def _unit(self, v: np.ndarray) -> np.ndarray:
        n = np.linalg.norm(v)
        return v / n if n > 1e-9 else self._rng.standard_normal(3) / np.sqrt(3.0)

    def _tilted(self, u: np.ndarray, max_deg: float) -> np.ndarray:
        return self._unit(u + np.tan(np.radians(max_deg)) * self._rng.uniform(-1, 1, 3))

    def _segment(self, t_s: float, p_WT: np.ndarray) -> None:
        rng = self._rng
        w = np.array([ADVERSARY_WEIGHTS[m] for m in self.modes])
        mode = "push" if not self.mode_log and "push" in self.modes else self.modes[rng.choice(len(w), p=w / w.sum())]
        out = self._unit(p_WT - self.p_WE_center)
        tangent = self._unit(np.cross(out, rng.standard_normal(3)))
        u = {"push": lambda: self._tilted(out, 15.0),
             "along": lambda: self._unit(tangent + 0.2 * out),
             "port_side": lambda: self._unit(tangent + 0.5 * out),
             "lens": lambda: self._tilted(self.p_W_lens - p_WT, 10.0),
             "random": lambda: self._unit(rng.standard_normal(3))}[mode]()
        self._v = rng.uniform(0.5, 1.0) * self.max_speed_mm_s * u
        self._roll = rng.uniform(-1.0, 1.0) * self.max_roll_rate if mode == "port_side" else 0.0
        self._until = t_s + rng.uniform(*self.segment_s)
        self.mode_log.append((float(t_s), mode))

    def __call__(self, t_s: float, p_WT, q) -> tuple[np.ndarray, float]:
        if t_s >= self._until:
            self._segment(t_s, np.asarray(p_WT, dtype=float))
        return self._v.copy(), self._roll
