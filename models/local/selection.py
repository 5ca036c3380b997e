"""When the adaptive model uses its local correction: a predictive test, like the
transition criteria's (models.adaptive.transition.PredictiveCriteria): every point is
predicted along its direction before it is absorbed, by the local field and by the
global quadric alone, where it starts a new scan line (its direction at least
`min_gap_deg` from the data so far: between scan lines is where the two differ); the local model is used once it holds `min_points` points and
its recent mean square prediction error is below `ratio` times the global model's
(exponential averages over about `memory` of those predictions), and given up again when it is no
longer below `keep_ratio` times it (reversible). On a regular eye the two predict alike
and the global model stays; over a detachment or a staphyloma the local one predicts the
next A-scans better. Past the pathology, on the healthy periphery a spiral ends on, the
two again predict more alike: given up at the taking-up ratio, the detached eye's local
model was dropped in the last 1 % of the paper's spiral pitch through the loop (18
revolutions, 15 mm/s, seed 0; the ratio 0.63-0.70 over the last 10 %), and the filter was
left the robust globe, scanned p95 506 um against the local model's 24 um. Kept while
merely no worse (1.0), a correction the myopic eye took up early in the paper's
simulation (seed 0, 14 % of the spiral) stayed to the end, MAE 2.6 um against the exact
ellipsoid's 0.6 um; with 0.85 it is given up there and the detached eye's is kept.
The global model improves along the spiral, and the averages remember it as it was:
over ~200 predictions across gaps (a quarter of the paper spiral's 744) the sphere's and
the young ellipsoid's errors before the transition (2-5 x the noise) keep the myopic
eye's correction to the end of the paper's spiral on 4 of 12 seeds (0-11; MAE 3.2-6.7 um
against its ellipsoid's 1.2-4.8 um). Over ~100 none does, but the same memory forgets a
detachment as the loop's spiral moves on to the healthy periphery: the detached eye's
ratio rises to 0.71-0.85 over the spiral's last 5 % (the faults campaign's time-offset
class, seed 0) against 0.28-0.32 over ~200, and its correction was given up at the
spiral's end (the robust globe's scanned p95 547 um against the correction's 28 um).
Averages that weigh the old predictions by the global quadric as it is now, not as it
was, would serve both; 200 keeps the loop's.
A point both models predict more than `outlier_mm` off counts for neither: 0.5 mm, the
least distance in front of the retina of a floater the sensor reports (planning.iioct).
One such floater, 1.2 mm short, 3.5 deg from the data, let through by the outlier gate as
an adversarial scenario began (`vitreoguard faults --shape detached --local-model`, class
floaters, seed 0, scenario 42), took the detached eye's mean square errors from 114 and
238 to 7,742 and 7,862 um^2 in one step: the local model was given up, the filter's sigma
over the detachment became the local and global surfaces' disagreement (0.92 mm at the
tip), and the tip, recovering towards where sigma was smaller, came 0.256 mm from the
retina.
"""
from __future__ import annotations

import numpy as np

from models.local.field_kernels import gap_errors


class LocalChoice:
    """The predictive test's state; `active` whether the local model is used."""

    def __init__(self, min_points: int = 400, ratio: float = 0.7, memory: float = 200.0, min_gap_deg: float = 2.0,
                 keep_ratio: float = 0.85, outlier_mm: float = 0.5):
        if not 0.0 < ratio <= keep_ratio:
            raise ValueError(f"LocalChoice needs 0 < ratio <= keep_ratio, got ratio={ratio}, keep_ratio={keep_ratio}")
        self.min_points, self.ratio, self.memory = int(min_points), float(ratio), float(memory)
        self.keep_ratio = float(keep_ratio)
        if not outlier_mm > 0.0:
            raise ValueError(f"LocalChoice needs outlier_mm > 0, got {outlier_mm}")
        self.outlier_mm = float(outlier_mm)
        self.min_gap_rad = float(np.radians(min_gap_deg))
        self.mse_local = self.mse_global = np.nan
        self.active = False

    def absorb(self, local, P: np.ndarray, shape, trend=None, shape_sd_mm=None) -> None:
        """Let `local` (a LocalRetinaModel) absorb the points P (N, 3) mm on the global `shape`
        (trend, shape_sd_mm: LocalRetinaModel.update's), and score its predictions of them,
        made before it absorbed them, against the global quadric's
        (models.local.field_kernels.predictions)."""
        scored = shape is not None and local.global_params is not None
        local.update(P, shape, trend, shape_sd_mm)
        if scored:
            el, eg, m = gap_errors(local.last_predictions, self.min_gap_rad, self.outlier_mm)  # predicted before they were absorbed
            if m:
                a = min(m / self.memory, 1.0)
                if np.isnan(self.mse_local):
                    self.mse_local, self.mse_global = el / m, eg / m
                else:
                    self.mse_local += a * (el / m - self.mse_local)
                    self.mse_global += a * (eg / m - self.mse_global)
        self.decide(local.n_points)

    def decide(self, n_points: int) -> bool:
        """Take up or give up the local model of n_points points from the prediction errors
        so far (`active`: below `ratio` x the global model's to take it up, below
        `keep_ratio` x to keep it)."""
        ratio = self.keep_ratio if self.active else self.ratio
        self.active = bool(n_points >= self.min_points and self.mse_local < ratio * self.mse_global)
        return self.active
