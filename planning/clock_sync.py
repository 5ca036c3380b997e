"""Synchronising the OCT stream with the robot's: the synchronisation motion and the
time-offset estimate (after Briel et al. 2025, who reach < 2.6 ms).

The motion: with the shaft through the trocar, the tip moves in and out along the beam
by a(t) = A sin(pi t / T) sin(2 pi f t) (an amplitude-modulated sinusoid: a unique
pattern, starting and ending at rest at the start posture). The beam keeps its direction
and stays on one retinal spot, so the measured distance follows the motion:
d(t_oct) = c + g s(t_oct - offset), where s is the beam origin's travel along the beam
from the robot's reported joint angles (robot clock), g about -1 (minus the cosine
between the true beam and the motion), and `offset` = OCT clock minus robot clock
(positive when the OCT stream lags).

The estimate: for each trial offset on a 0.25 ms grid over +-max_offset the best (c, g)
by linear least squares, the offset with the smallest residual, then refined below the
grid by a bounded scalar minimisation (scipy); one re-fit without the samples beyond
5 robust SDs (a floater, a wrong extraction). With 1 mm amplitude at 2 Hz the motion runs
up to 12 mm/s: a 0.5 ms error leaves 6 um RMS of unexplained residual over thousands of
samples, far above the 10-20 um extraction noise divided by their square root.

Units: mm, s, rad.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar

from planning.closed_form import shaft_ik

SYNC_AMPLITUDE_MM = 1.0
SYNC_CARRIER_HZ = 2.0
SYNC_DURATION_S = 3.0
GRID_STEP_S = 0.25e-3
# The synchronisation segment in the robot's stream: the beam within this angle of its
# direction at the segment's start and its origin within this distance of the beam's line.
SEGMENT_ANGLE_RAD = np.radians(0.5)
SEGMENT_LATERAL_MM = 0.1
# ... moving along the beam by at least this much, with this many reversals of this size.
SEGMENT_MIN_TRAVEL_MM = 0.3
SEGMENT_MIN_REVERSALS = 4
REVERSAL_MM = 0.05
GAIN_RANGE = (-1.2, -0.8)
SMOOTH_S = 0.025


class SyncError(ValueError):
    """The recording has no usable synchronisation segment (the message says why)."""


def sync_axial_mm(t_s, amplitude_mm: float = SYNC_AMPLITUDE_MM, carrier_hz: float = SYNC_CARRIER_HZ,
                  duration_s: float = SYNC_DURATION_S) -> np.ndarray:
    """(M,) mm: the synchronisation motion a(t) along the beam at times t_s (M,) s from
    its start (0 outside [0, duration_s])."""
    t = np.asarray(t_s, dtype=float)
    a = amplitude_mm * np.sin(np.pi * t / duration_s) * np.sin(2.0 * np.pi * carrier_hz * t)
    return np.where((t >= 0.0) & (t <= duration_s), a, 0.0)


def sync_joint_path(robot, q0, t_s, **motion) -> np.ndarray:
    """(M, 6) rad: joint angles that move the tip of `robot` (planning.Robot) from the
    posture q0 (6,) rad along its shaft by `sync_axial_mm`(t_s, **motion) (the shaft
    keeps its direction, so it stays on the trocar's line), closed-form IK on q0's branch
    (each sample the solution nearest the previous one). Raises ValueError when a
    sample is out of reach or leaves the joint limits."""
    q0 = np.asarray(q0, dtype=float)
    R_WF, p_WF = robot.pose("F", q0)
    u = R_WF[:, 0]  # the shaft: the flange x axis
    p_T0 = robot.point("T", np.zeros(3), q0)
    out = np.empty((len(t_s), 6))
    q = q0
    for m, a in enumerate(sync_axial_mm(t_s, **motion)):
        cands = shaft_ik(robot.arm, p_T0 + a * u, u, q0[5])
        if not len(cands):
            raise ValueError(f"the synchronisation motion leaves the arm's reach at {a:+.3f} mm along the shaft")
        wrapped = q + np.angle(np.exp(1j * (cands - q)))  # each candidate's angles nearest q's
        q = wrapped[np.argmin(np.abs(wrapped - q).max(axis=1))]
        if np.any(q < robot.q_lower) or np.any(q > robot.q_upper):
            raise ValueError("the synchronisation motion leaves the joint limits")
        out[m] = q
    return out


def find_sync_segment(O, U) -> tuple[int, int]:
    """(first, stop) indices of the first run of robot samples (beam origins O and unit
    directions U (K, 3) in W from the reported joints) in which the beam keeps its
    direction (SEGMENT_ANGLE_RAD) and line (SEGMENT_LATERAL_MM) and its origin moves along
    it by SEGMENT_MIN_TRAVEL_MM or more with SEGMENT_MIN_REVERSALS reversals of
    REVERSAL_MM. Raises SyncError when there is none."""
    O, U = np.asarray(O, dtype=float), np.asarray(U, dtype=float)
    K, i, best = len(O), 0, (0.0, 0)
    while i < K - 1:
        stop = _run_end(O, U, i)
        s = (O[i:stop] - O[i]) @ U[i]
        travel, reversals = float(np.ptp(s)), _reversals(s, REVERSAL_MM)
        if travel >= SEGMENT_MIN_TRAVEL_MM and reversals >= SEGMENT_MIN_REVERSALS:
            return i, stop
        best = max(best, (travel, reversals))
        i = max(stop, i + 1)
    raise SyncError(f"no synchronisation segment: no stretch of the robot's motion moves the tip along the beam "
                    f"(direction within {np.degrees(SEGMENT_ANGLE_RAD):g} deg) by >= {SEGMENT_MIN_TRAVEL_MM} mm with "
                    f">= {SEGMENT_MIN_REVERSALS} reversals (best: {best[0]:.3f} mm, {best[1]} reversals); the recording "
                    "must contain the amplitude-modulated in-and-out motion (vitreoguard record makes one)")


def _run_end(O: np.ndarray, U: np.ndarray, i: int, chunk: int = 2048) -> int:
    """The first index after i at which the beam leaves sample i's direction or line."""
    K = len(O)
    start = i + 1
    while start < K:
        j = np.arange(start, min(start + chunk, K))
        dO = O[j] - O[i]
        s = dO @ U[i]
        bad = (U[j] @ U[i] < np.cos(SEGMENT_ANGLE_RAD)) | (np.linalg.norm(dO - s[:, None] * U[i], axis=1) > SEGMENT_LATERAL_MM)
        if bad.any():
            return int(j[np.argmax(bad)])
        start = int(j[-1]) + 1
    return K


def _reversals(s: np.ndarray, hysteresis: float) -> int:
    """Number of direction reversals of s, each after a swing of at least `hysteresis`."""
    count, direction, extreme = 0, 0, float(s[0]) if len(s) else 0.0
    for v in s.tolist():
        if direction == 0:
            if abs(v - extreme) > hysteresis:
                direction, extreme = (1 if v > extreme else -1), v
        elif direction * (v - extreme) > 0:
            extreme = v
        elif direction * (extreme - v) > hysteresis:
            count, direction, extreme = count + 1, -direction, v
    return count


@dataclass(frozen=True)
class OffsetEstimate:
    """The time offset `offset_s` (OCT clock minus robot clock, s), the fit's gain
    (distance per mm of travel, about -1) and constant (mm), its residual RMS (mm) and
    number of samples, and the residual RMS (mm) over the coarse grid of trial offsets
    `grid_s` (for the plot)."""

    offset_s: float
    gain: float
    constant_mm: float
    residual_rms_mm: float
    n_samples: int
    grid_s: np.ndarray
    grid_rms_mm: np.ndarray


def _smoothed(s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The travel s (K,) mm at times t (K,) s with the encoder noise smoothed out: a cubic
    Savitzky-Golay filter over SMOOTH_S (zero phase; it bends a 2 Hz carrier by < 1e-4
    of its amplitude). Unsmoothed, the noise of an interpolated sample depends on where it
    falls between two joint states (its variance (1 - f)^2 + f^2 of theirs), so the
    residual ripples with the OCT's sample period and pulls the offset by ~0.1 ms."""
    from scipy.signal import savgol_filter

    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    window = int(SMOOTH_S / dt) // 2 * 2 + 1
    return savgol_filter(s, window, 3) if window >= 5 and len(s) > window else s


def _fit_at(tau: float, t_oct, d, t_robot, s_robot) -> tuple[float, float, float]:
    """(residual sum of squares, gain, constant) of d = c + g s(t_oct - tau)."""
    s = np.interp(t_oct - tau, t_robot, s_robot)
    sm, dm = s.mean(), d.mean()
    ds, dd = s - sm, d - dm
    sxx = float(ds @ ds)
    g = float(ds @ dd) / sxx if sxx > 0 else 0.0
    r = dd - g * ds
    return float(r @ r), g, dm - g * sm


def estimate_time_offset(t_oct, d, t_robot, s_robot, max_offset_s: float = 0.1) -> OffsetEstimate:
    """The OCT-robot time offset (module docstring) from the distances d (N,) mm at OCT
    times t_oct (N,) s and the beam's travel s_robot (K,) mm at robot times t_robot (K,) s
    of the synchronisation segment, searched over +-max_offset_s. Only OCT samples whose
    robot time lies inside the segment for every trial offset are used. Raises SyncError
    when fewer than 200 remain, or the distance does not follow the motion."""
    t_oct, d = np.asarray(t_oct, dtype=float), np.asarray(d, dtype=float)
    t_robot, s_robot = np.asarray(t_robot, dtype=float), _smoothed(np.asarray(s_robot, dtype=float), t_robot)
    inside = (t_oct - max_offset_s >= t_robot[0]) & (t_oct + max_offset_s <= t_robot[-1]) & np.isfinite(d)
    if inside.sum() < 200:
        raise SyncError(f"only {int(inside.sum())} valid OCT samples fall inside the synchronisation segment "
                        f"({t_robot[0]:.3f}-{t_robot[-1]:.3f} s robot time, +-{1e3 * max_offset_s:g} ms): the streams do "
                        "not overlap there, or the A-scans hold no retina")
    t, y = t_oct[inside], d[inside]
    grid = np.arange(-max_offset_s, max_offset_s + 0.5 * GRID_STEP_S, GRID_STEP_S)
    for _ in range(2):  # the second pass without the first's outliers
        rss = np.array([_fit_at(tau, t, y, t_robot, s_robot)[0] for tau in grid])
        k = int(np.argmin(rss))
        lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
        tau = float(minimize_scalar(lambda x: _fit_at(x, t, y, t_robot, s_robot)[0], bounds=(lo, hi), method="bounded",
                                    options={"xatol": 1e-7}).x)
        _, g, c = _fit_at(tau, t, y, t_robot, s_robot)
        r = y - c - g * np.interp(t - tau, t_robot, s_robot)
        mad = 1.4826 * float(np.median(np.abs(r - np.median(r))))
        keep = np.abs(r) <= max(5.0 * mad, 1e-6)
        grid_rms = np.sqrt(rss / len(y))
        t, y = t[keep], y[keep]
    if not (GAIN_RANGE[0] <= g <= GAIN_RANGE[1]):
        raise SyncError(f"the OCT distance does not follow the synchronisation motion: gain {g:+.3f} mm/mm, expected "
                        f"{GAIN_RANGE[0]:g} to {GAIN_RANGE[1]:g} (the wrong A-scan topic, or no retina in the beam)")
    r = y - c - g * np.interp(t - tau, t_robot, s_robot)
    return OffsetEstimate(tau, g, c, float(np.sqrt(np.mean(r * r))), len(y), grid, grid_rms)
