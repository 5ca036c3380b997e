"""The local model's standard deviation calibrated on its own held-out predictions.

Every point is predicted along its direction before the model absorbs it
(models.local.field_kernels.predictions): its error against the blended field, in units
of the field's uncalibrated sd, is a draw of the model's error at that point's gap (the
angle from the data so far, as the field blends it). A point that starts a new scan line
a few degrees from the last is exactly the prediction the barrier relies on between
scan lines. Per gap knot (CAL_KNOTS_RAD: 0-15 deg) a histogram of |error| / (k sd)
gives the factor that makes `quantile` of those errors lie within k calibrated sd; a
point's count is split linearly between the two knots around its gap (knot_at, the
field's own interpolation). The factors
never shrink the sd (at least 1) and never fall with the gap (a knot with fewer than
`min_count` points, or a smaller factor, takes the largest one nearer the data): errors
grow away from the data, and a knot the scan has not reached yet is not evidence of a
smaller one. Old evidence fades: a knot's counts halve once they pass `memory`, so the
factors follow the model as it improves.

Why: the sd's model (models.local.grid) is a posterior plus bias terms, each a bound
derived from the data near a node; on a detachment's flank the quadratics' error between
scan lines 2-10 deg apart outgrew it (3 sd covered 97-98 % there, all misses on the
unsafe side, up to 8 sd), while the model's own predictions across those gaps show the
error as it is. Calibrating a predictive sd on held-out errors is the standard check of
a probabilistic forecast (Gneiting, Balabdaoui & Raftery, J. R. Stat. Soc. B 69, 2007:
calibration as the agreement of forecast quantiles with the observations).
Units: mm, rad.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models.local.field_kernels import N_CAL, knot_at


@njit(cache=True)
def absorb_errors(pred, k, width, hist, count, memory):
    """Add the rows of `pred` (M, 6: models.local.field_kernels.predictions; NaN rows
    skipped) to the knots' histograms hist (N_CAL, cells) of |error| / (k sd) in cells
    `width` wide (the last one open), their totals in count (N_CAL,); a knot whose total
    passes `memory` has its counts halved."""
    cells = hist.shape[1]
    for i in range(pred.shape[0]):
        r, rl, sd, gap = pred[i, 0], pred[i, 1], pred[i, 2], pred[i, 3]
        if not (np.isfinite(r) and np.isfinite(rl) and sd > 0.0 and np.isfinite(gap)):
            continue
        c = min(int(abs(rl - r) / (k * sd) / width), cells - 1)
        j, t = knot_at(gap)
        for kn, w in ((j, 1.0 - t), (j + 1, t)):
            if w <= 0.0:
                continue
            hist[kn, c] += w
            count[kn] += w
            if count[kn] > memory:
                hist[kn, :] *= 0.5
                count[kn] *= 0.5


@njit(cache=True)
def knot_factors(hist, count, width, quantile, min_count, out):
    """out (N_CAL,): per knot the upper edge of the cell where the cumulative count passes
    `quantile` of the total (the sd factor), at least 1 and at least the factor of every
    knot nearer the data; a knot with fewer than `min_count` points takes its inner
    neighbour's."""
    f = 1.0
    for kn in range(hist.shape[0]):
        if count[kn] >= min_count:
            target, s = quantile * count[kn], 0.0
            for c in range(hist.shape[1]):
                s += hist[kn, c]
                if s >= target:
                    f = max(f, (c + 1) * width)
                    break
        out[kn] = f
    return out


class SigmaCalibration:
    """The sd factors (N_CAL,) at CAL_KNOTS_RAD that make `quantile` of the model's held-out
    errors lie within k sd (k the barrier's: safety.constraints.point_barrier's sigma
    factor, 3). `absorb(pred)` takes field_kernels.predictions' rows; `factors` the
    current ones (ones until a knot holds `min_count` points)."""

    def __init__(self, k: float = 3.0, quantile: float = 0.99, min_count: float = 100.0, memory: float = 20000.0,
                 max_factor: float = 8.0, width: float = 0.05):
        if not (k > 0 and 0.5 <= quantile < 1.0 and min_count > 0 and memory > 2 * min_count and max_factor > 1
                and 0 < width < max_factor):
            raise ValueError(f"SigmaCalibration: k {k} > 0, quantile {quantile} in [0.5, 1), min_count {min_count} > 0, "
                             f"memory {memory} > 2 min_count, max_factor {max_factor} > 1, width {width} in (0, max_factor)")
        self.k, self.quantile, self.min_count, self.memory, self.width = float(k), float(quantile), float(min_count), \
            float(memory), float(width)
        self.hist = np.zeros((N_CAL, int(np.ceil(max_factor / width))))
        self.count = np.zeros(N_CAL)
        self._factors = np.ones(N_CAL)

    def absorb(self, pred: np.ndarray) -> None:
        absorb_errors(pred, self.k, self.width, self.hist, self.count, self.memory)

    @property
    def factors(self) -> np.ndarray:
        """(N_CAL,) the sd factors at CAL_KNOTS_RAD (a fresh array)."""
        return knot_factors(self.hist, self.count, self.width, self.quantile, self.min_count, self._factors).copy()
