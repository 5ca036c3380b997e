"""Innovation gate: keep floaters and mis-segmentations out of the eye model.

`OutlierGate` is the configuration (and the decision rule); `GateState` is one model's
running state: the last accepted point, the recent distances behind the robust
residual, the run of consecutive rejections, and the counters.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models._validation import check_count, check_positive
from models.ellipsoid_fit import LENGTH_SCALE_MM
from models.extrapolation import sampson_distance

RESIDUAL_REFRESH = 16  # accepted points between refreshes of the robust residual (a median)


@dataclass(frozen=True)
class OutlierGate:
    """Reject a new point whose distance to the current model exceeds
    max(`min_gate_mm`, `k_residual` x the model's robust residual), once the model rests
    on `min_points` points. The residual is robust (1.4826 x the median absolute distance
    of the last `window` accepted points to the model), so outliers that got in cannot
    open the gate for more. Before the model has `min_points`, and always in addition,
    a point more than `max_jump_mm` from the last accepted one is rejected: A-scans come
    at 2 kHz along a continuous path, so consecutive retinal points lie micrometres to
    tenths of a millimetre apart, while a floater or a wrong peak jumps by millimetres.

    A floater or a wrong peak is an isolated excursion; real retina that the model does
    not fit (a detachment, a staphyloma) keeps arriving. So a run of more than
    `max_consecutive` rejected A-scans (5 ms at 2 kHz by default) is taken as structure
    and accepted: the gate never blinds the model to retina that is really there.
    """

    k_residual: float = 6.0
    min_gate_mm: float = 0.15
    min_points: int = 30
    max_consecutive: int = 10
    window: int = 64
    max_jump_mm: float = 1.0

    def __post_init__(self):
        check_positive(self, "k_residual", "min_gate_mm", "max_jump_mm")
        check_count(self, "min_points", "max_consecutive")
        check_count(self, "window", minimum=1)

    def accept(self, distance_mm, points, last, residual_mm: float, n_model_points: int, run: int):
        """(keep flags, new count of consecutive rejections, last kept point) for points
        (sequence of [x, y, z] mm, in A-scan order) at `distance_mm` from a model with
        robust residual `residual_mm`; each point's jump is measured from the last point
        KEPT before it (`last` on entry), so a rejected floater never counts as the
        reference for the next A-scan. While more than `max_consecutive` far points have
        come in a row, the gate stays open: that is retina, not a floater."""
        use_model = n_model_points >= self.min_points and residual_mm < float("inf")
        gate = max(self.min_gate_mm, self.k_residual * residual_mm) if use_model else float("inf")
        keep = []
        lx, ly, lz = last
        for d, (px, py, pz) in zip(distance_mm, points):
            jump = ((px - lx) ** 2 + (py - ly) ** 2 + (pz - lz) ** 2) ** 0.5
            near = jump <= self.max_jump_mm and d <= gate
            run = 0 if near else run + 1
            k = near or run > self.max_consecutive
            if k:
                lx, ly, lz = px, py, pz
            keep.append(k)
        return keep, run, [lx, ly, lz]


def _median(x: np.ndarray) -> float:
    """The median of x (inf when empty), by partition: a fifth of np.median's overhead on
    the gate's 64-value window."""
    n = len(x)
    if n == 0:
        return float("inf")
    k = n // 2
    part = np.partition(x, (k - 1, k) if n % 2 == 0 else k)
    return float(part[k]) if n % 2 else 0.5 * (float(part[k - 1]) + float(part[k]))


def _sampson_one(v: list, x: float, y: float, z: float) -> float:
    """|Q| / |grad Q| of one point (scaled coordinates) for quadric coefficients v, in floats."""
    a, b, c, f, g, h, p, q, r, d = v
    Q = a * x * x + b * y * y + c * z * z + 2 * (f * y * z + g * x * z + h * x * y + p * x + q * y + r * z) + d
    gx, gy, gz = a * x + h * y + g * z + p, h * x + b * y + f * z + q, g * x + f * y + c * z + r
    grad = 2.0 * (gx * gx + gy * gy + gz * gz) ** 0.5
    return abs(Q) / grad if grad > 0 else float("inf")


class GateState:
    """One model's gate: `admit(P, quadric, p0, n_model_points)` returns the points of P
    (N, 3) mm to keep and counts the others in `n_rejected`. `quadric` (10,) is the current
    model in the fits' scaled coordinates about `p0` (None before a model exists)."""

    def __init__(self, gate: OutlierGate):
        self.gate = gate
        self.n_rejected = 0
        self._run = 0
        self._last: list | None = None
        self._recent = np.empty(gate.window)  # |distance| of recently accepted points, mm
        self._n_recent = 0
        self._refresh_at = 0  # count of accepted points at which the residual is next refreshed
        self._residual = np.inf

    @staticmethod
    def _distances(P: np.ndarray, quadric, p0) -> list:
        """Distance (mm) of each point of P to the model (0 before a model exists)."""
        if quadric is None:
            return [0.0] * len(P)
        if len(P) == 1:  # the per-A-scan path, in plain floats
            px, py, pz = P[0].tolist()
            ox, oy, oz = p0.tolist()
            L = LENGTH_SCALE_MM
            return [L * _sampson_one(quadric.tolist(), (px - ox) / L, (py - oy) / L, (pz - oz) / L)]
        return (LENGTH_SCALE_MM * sampson_distance(quadric, (P - p0) / LENGTH_SCALE_MM)).tolist()

    def admit(self, P: np.ndarray, quadric, p0, n_model_points: int) -> np.ndarray:
        if len(P) == 0:
            return P
        first = self._last is None
        if first:  # nothing to compare the very first point with: it becomes the reference
            self._last = P[0].tolist()
        d = self._distances(P, quadric, p0)
        if self._n_recent >= self._refresh_at:  # the median is refreshed every REFRESH points, not per point
            self._residual = 1.4826 * _median(self._recent[: min(self._n_recent, len(self._recent))])
            self._refresh_at = self._n_recent + RESIDUAL_REFRESH
        keep, self._run, self._last = self.gate.accept(d, P.tolist(), self._last, self._residual, n_model_points,
                                                       self._run)
        for di, k in zip(d, keep):
            if k:
                self._recent[self._n_recent % len(self._recent)] = di
                self._n_recent += 1
        if all(keep):
            return P
        self.n_rejected += keep.count(False)
        return P[np.array(keep)]
