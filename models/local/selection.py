"""When the adaptive model uses its local correction: a predictive test, like the
transition criteria's (models.adaptive.transition.PredictiveCriteria): every point is
predicted along its direction before it is absorbed, by the local field and by the global
quadric alone; where it starts a new scan line (its direction at least `min_gap_deg` from
the data so far: between scan lines is where the two differ) the prediction is stored. The
local model is used once it holds `min_points` points and its mean square error over the
stored predictions is below `ratio` times the global quadric's, and given up again when it
is no longer below `keep_ratio` times it (reversible). The local field's errors count as it
predicted them; the global quadric's are those of the quadric as it is now: every stored
prediction is scored again against the current one, a pass over them every
`rescore_points` points, spread over the updates (rows x points / rescore_points per
update: ~150 rows per packet of 20 A-scans at the end of the loop's spiral, a few per
single A-scan), and the averages are each pass's. At most `max_rows` are kept, a regular
subsample (every other one dropped and the stride doubled when full).
Why the current quadric: the global quadric improves along the spiral, and averages that
remember its errors as they were hold the sphere's and the young ellipsoid's (2-5 x the
noise) long after. Over the last ~200 predictions (exponential averages) the myopic eye's
correction stayed to the end of the paper's spiral on 4 of 12 seeds (0-11; MAE 3.2-6.7 um
against its ellipsoid's 1.2-4.8 um); over ~100, a detachment was forgotten once the loop's
spiral moved on to the healthy periphery (the faults campaign's time-offset class, seed 0:
the ratio rose to 0.71-0.85 over the spiral's last 5 % and the correction was given up,
the robust globe's scanned p95 547 um against the correction's 28 um). Re-scored and over
all of them, on the paper's spiral (seeds 0-11) the regular eyes end on their ellipsoid
and the detached eye, the staphyloma and the pointed eye on the local model on every seed;
over the last 400 only, the time-offset build gave its correction up again (p95 525 um).
On a regular eye the two predict alike and the global model stays; over a detachment or a
staphyloma the local one predicts the next A-scans better.
Past the pathology the two again predict more alike: given up at the taking-up ratio, the
detached eye's local model was dropped in the last 1 % of the paper's spiral pitch through
the loop (18 revolutions, 15 mm/s, seed 0) and the filter left the robust globe, scanned
p95 506 um against the local model's 24 um; hence `keep_ratio` 0.85 (kept while merely no
worse, 1.0, a correction the myopic eye took up early in the paper's simulation stayed to
the end).
A point both models predict more than `outlier_mm` off counts for neither: 0.5 mm, the
least distance in front of the retina of a floater the sensor reports (planning.iioct).
One such floater, 1.2 mm short, 3.5 deg from the data, let through by the outlier gate as
an adversarial scenario began (`vitreoguard faults --shape detached --local-model`, class
floaters, seed 0, scenario 42), took the detached eye's mean square errors from 114 and
238 to 7,742 and 7,862 um^2 in one step: the local model was given up, the filter's sigma
over the detachment became the local and global surfaces' disagreement (0.92 mm at the
tip), and the tip, recovering towards where sigma was smaller, came 0.256 mm from the
retina. Such a point is not stored; a stored one the current quadric mispredicts by that
much too is left out of the pass.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models.local.geometry import global_radius


@njit(cache=True)
def take_gap_rows(pred, P, c0, min_gap, outlier, U, r, el2, n, seen, stride):
    """Store the rows of `pred` (models.local.field_kernels.predictions) that predict across
    a gap (the nearest node at least `min_gap` rad from the data), less those both models
    predicted more than `outlier` mm off, every `stride`-th of them counted by `seen`: the
    point's direction from c0 in U (., 3), its measured radius in r and the local field's
    squared error in el2 (mm^2), from row n on while there is room. Returns (n, seen)."""
    for i in range(pred.shape[0]):
        if n == U.shape[0]:
            break
        if pred[i, 5] >= min_gap:
            a, b = pred[i, 0] - pred[i, 1], pred[i, 0] - pred[i, 4]
            if abs(a) > outlier and abs(b) > outlier:
                continue
            seen += 1
            if (seen - 1) % stride:
                continue
            d = pred[i, 0]
            for j in range(3):
                U[n, j] = (P[i, j] - c0[j]) / d
            r[n] = d
            el2[n] = a * a
            n += 1
    return n, seen


@njit(cache=True)
def rescore_rows(U, r, el2, i0, i1, c0, gp, outlier2, sums):
    """sums (3,) += (local squared errors, the global quadric gp's squared errors now, count)
    over the stored rows [i0, i1), less those both mispredict by more than outlier2 mm^2
    (and any gp cannot answer: c0 outside it)."""
    for i in range(i0, i1):
        e = r[i] - global_radius(c0, gp, U[i, 0], U[i, 1], U[i, 2])
        e2 = e * e
        if not (e2 <= outlier2 or el2[i] <= outlier2):
            continue
        sums[0] += el2[i]
        sums[1] += e2
        sums[2] += 1.0


class LocalChoice:
    """The predictive test's state; `active` whether the local model is used;
    `mse_local`, `mse_global` the mean square errors (mm^2) it was last decided by."""

    def __init__(self, min_points: int = 400, ratio: float = 0.7, rescore_points: int = 400, min_gap_deg: float = 2.0,
                 keep_ratio: float = 0.85, outlier_mm: float = 0.5, max_rows: int = 4096):
        if not 0.0 < ratio <= keep_ratio:
            raise ValueError(f"LocalChoice needs 0 < ratio <= keep_ratio, got ratio={ratio}, keep_ratio={keep_ratio}")
        if not outlier_mm > 0.0:
            raise ValueError(f"LocalChoice needs outlier_mm > 0, got {outlier_mm}")
        if not (isinstance(rescore_points, (int, np.integer)) and rescore_points >= 1):
            raise ValueError(f"LocalChoice needs an integer rescore_points >= 1, got {rescore_points!r}")
        if not (isinstance(max_rows, (int, np.integer)) and max_rows >= 2):
            raise ValueError(f"LocalChoice needs an integer max_rows >= 2, got {max_rows!r}")
        self.min_points, self.ratio, self.keep_ratio = int(min_points), float(ratio), float(keep_ratio)
        self.rescore_points, self.max_rows = int(rescore_points), int(max_rows)
        self.outlier_mm = float(outlier_mm)
        self.min_gap_rad = float(np.radians(min_gap_deg))
        self.mse_local = self.mse_global = np.nan
        self.active = False
        self._U, self._r, self._el2 = np.empty((64, 3)), np.empty(64), np.empty(64)
        self.n_rows = 0  # stored predictions across gaps: every stride-th of the seen ones
        self._seen, self._stride = 0, 1
        self._cursor, self._credit = 0, 0.0  # the running re-scoring pass: next row, rows owed
        self._sums = np.zeros(3)

    def absorb(self, local, P: np.ndarray, shape, trend=None, shape_sd_mm=None) -> None:
        """Let `local` (a LocalRetinaModel) absorb the points P (N, 3) mm on the global `shape`
        (trend, shape_sd_mm: LocalRetinaModel.update's), store its predictions of them across
        gaps, made before it absorbed them (models.local.field_kernels.predictions), and
        re-score rows_owed of the stored ones against the global quadric as it is now."""
        scored = shape is not None and local.global_params is not None
        local.update(P, shape, trend, shape_sd_mm)
        if scored:
            self._store(local.last_predictions, P, local.center)
        if self.n_rows and local.global_params is not None:
            self._rescore(len(P), local.center, local.global_params)
        self.decide(local.n_points)

    def _store(self, pred: np.ndarray, P: np.ndarray, c0: np.ndarray) -> None:
        if self.n_rows + len(pred) > len(self._r):
            if len(self._r) < self.max_rows:
                size = min(2 * len(self._r) + len(pred), self.max_rows)
                self._U = np.concatenate([self._U[:self.n_rows], np.empty((size - self.n_rows, 3))])
                self._r = np.concatenate([self._r[:self.n_rows], np.empty(size - self.n_rows)])
                self._el2 = np.concatenate([self._el2[:self.n_rows], np.empty(size - self.n_rows)])
            if self.n_rows + len(pred) > len(self._r):  # full: every other row kept, the stride doubled
                k = (self.n_rows + 1) // 2
                self._U[:k], self._r[:k], self._el2[:k] = (self._U[:self.n_rows:2].copy(), self._r[:self.n_rows:2].copy(),
                                                           self._el2[:self.n_rows:2].copy())
                self.n_rows, self._cursor, self._stride = k, 0, 2 * self._stride
                self._sums[:] = 0.0
        self.n_rows, self._seen = take_gap_rows(pred, P, c0, self.min_gap_rad, self.outlier_mm, self._U, self._r,
                                                self._el2, self.n_rows, self._seen, self._stride)

    def _rescore(self, n_points: int, c0: np.ndarray, gp: np.ndarray) -> None:
        """Re-score the rows owed for n_points points (all of them every rescore_points points;
        at once while no pass has ended yet); at a pass's end the averages are its sums."""
        self._credit += self.n_rows * n_points / self.rescore_points
        todo = int(self._credit)
        if np.isnan(self.mse_global):
            todo = self.n_rows - self._cursor
        self._credit -= min(todo, self._credit)
        while todo > 0:
            i1 = min(self._cursor + todo, self.n_rows)
            rescore_rows(self._U, self._r, self._el2, self._cursor, i1, c0, gp, self.outlier_mm ** 2, self._sums)
            todo -= i1 - self._cursor
            self._cursor = i1
            if i1 == self.n_rows:
                if self._sums[2] > 0:
                    self.mse_local, self.mse_global = self._sums[0] / self._sums[2], self._sums[1] / self._sums[2]
                self._sums[:] = 0.0
                self._cursor = 0
                break

    def decide(self, n_points: int) -> bool:
        """Take up or give up the local model of n_points points from the prediction errors
        so far (`active`: below `ratio` x the global model's to take it up, below
        `keep_ratio` x to keep it)."""
        ratio = self.keep_ratio if self.active else self.ratio
        self.active = bool(n_points >= self.min_points and self.mse_local < ratio * self.mse_global)
        return self.active
