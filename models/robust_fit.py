"""Robust incremental ellipsoid fit: the healthy globe of an eye with a local pathology.

A detachment or a staphyloma is a patch of retina that no quadric follows; the plain
least-squares fit bends towards it and then extrapolates badly to the retina the fibre
has not seen. This fit down-weights such patches with Tukey's biweight on each point's
first-order (Sampson) distance d from the current fit,

    w = (1 - (d / c)^2)^2 for |d| < c, else 0,   c = `tukey_factor` x `noise_sd_mm`,

so that points within a few noise SDs of the ellipsoid count almost fully and points on a
pathology (millimetres off) not at all: the fit minimises v^T S_w v over the weighted
scatter matrix S_w = sum w m m^T (models.ellipsoid_fit) by iteratively reweighted least
squares (IRLS).

Cost: a new point gets its weight from the current fit and joins S_w (O(1), one compiled
call); all weights are recomputed from the stored points, `iterations` IRLS steps
warm-started from the current fit, whenever the point count has grown by `refit_growth`
since the last reweighting (and by at least `min_refit_points`). A reweighting costs O(N)
but they come geometrically rarer, so the amortised cost per point is O(1): about
iterations x (1 + 1 / refit_growth) design rows. Memory: the points, N x 3 floats.
Coordinates as in models.ellipsoid_fit: origin at the first point, lengths divided by
LENGTH_SCALE_MM.

What the transition criteria see (models.transition): `S` is the scatter matrix of the
points weighted as they arrived, by the fit of that moment (prequential: a point the
ellipsoid did not predict is left out of the criteria's residuals and windows for good,
and S[9, 9] over the number of points is the share it predicted); `restarted_at` is the
point count of the last restart from the plain fit, where the fit's history begins anew
(a scan that starts on a pathology first fits the pathology, and the fit jumps to the
healthy globe once that is the larger part of the data).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from models._validation import check_count, check_positive
from models.ellipsoid_fit import LENGTH_SCALE_MM, EllipsoidFit, design_rows, fit_scatter
from models.extrapolation import sampson_distance


@dataclass(frozen=True)
class RobustFitConfig:
    """Settings of RobustEllipsoidFit. `noise_sd_mm` (mm): SD of the distance noise;
    `tukey_factor`: the biweight's cut-off in noise SDs (4.685: 95 % efficiency on
    Gaussian noise); `refit_growth`: relative growth of the point count between full
    reweightings; `min_refit_points`: fewest new points between them; `iterations`: IRLS
    steps per reweighting; `min_inlier_fraction`: when the warm start leaves fewer of the
    points than this with any weight, the reweighting restarts from the plain fit."""

    noise_sd_mm: float = 0.020
    tukey_factor: float = 4.685
    refit_growth: float = 0.05
    min_refit_points: int = 25
    iterations: int = 10
    min_inlier_fraction: float = 0.5

    def __post_init__(self):
        check_positive(self, "noise_sd_mm", "tukey_factor", "refit_growth")
        check_count(self, "min_refit_points", minimum=1)
        check_count(self, "iterations", minimum=1)
        if not (np.isfinite(self.min_inlier_fraction) and 0.0 < self.min_inlier_fraction <= 1.0):
            raise ValueError(f"min_inlier_fraction must be in (0, 1], got {self.min_inlier_fraction}")

    @property
    def cutoff_mm(self) -> float:
        """Distance (mm) beyond which a point has no weight."""
        return self.tukey_factor * self.noise_sd_mm


def biweight(d_mm: np.ndarray, cutoff_mm: float) -> np.ndarray:
    """Tukey's biweight (1 - (d / c)^2)^2 of distances d (mm), 0 beyond the cut-off c (mm)."""
    u = np.minimum(np.abs(d_mm) / cutoff_mm, 1.0)
    return (1.0 - u * u) ** 2


@njit(cache=True)
def _add_weighted_rows(S, S_w, X, v, cutoff, w_out):
    """For scaled points X (N, 3): S += sum w m m^T and S_w += sum w m m^T in place, with
    w the biweight of the Sampson distance from quadric v (10,) (cut-off `cutoff`, scaled
    units; an all-zero v gives every point weight 1); the weights go to w_out (N,)."""
    m = np.empty(10)
    has_fit = np.any(v != 0.0)
    for n in range(X.shape[0]):
        x, y, z = X[n, 0], X[n, 1], X[n, 2]
        m[0], m[1], m[2], m[3], m[4] = x * x, y * y, z * z, 2 * y * z, 2 * x * z
        m[5], m[6], m[7], m[8], m[9] = 2 * x * y, 2 * x, 2 * y, 2 * z, 1.0
        w = 1.0
        if has_fit:
            q = 0.0
            for i in range(10):
                q += m[i] * v[i]
            gx = 2.0 * (v[0] * x + v[5] * y + v[4] * z + v[6])
            gy = 2.0 * (v[5] * x + v[1] * y + v[3] * z + v[7])
            gz = 2.0 * (v[4] * x + v[3] * y + v[2] * z + v[8])
            g = np.sqrt(gx * gx + gy * gy + gz * gz)
            u = min(abs(q) / g / cutoff, 1.0) if g > 0.0 else 1.0
            w = (1.0 - u * u) ** 2
        w_out[n] = w
        for i in range(10):
            for j in range(i, 10):
                p = w * m[i] * m[j]
                S[i, j] += p
                S_w[i, j] += p
                if j != i:
                    S[j, i] += p
                    S_w[j, i] += p


class RobustEllipsoidFit:
    """Drop-in for IncrementalEllipsoidFit (`add`, `fit`, `S`, `p0`, `last_ok`,
    `n_points`) with biweight-reweighted points (module doc).

    `S` is the scatter matrix of the points weighted as they arrived (module doc: what
    the criteria see), `S_weighted` the one with the current weights, S_w, that the fit
    minimises (scaled coordinates); `weights` (N,) the current weight in [0, 1] of every
    point received; `n_reweightings` how many full reweightings have run; `restarted_at`
    the point count at the last restart from the plain fit (0: none).
    """

    def __init__(self, config: RobustFitConfig | None = None):
        self.config = RobustFitConfig() if config is None else config
        self.S = np.zeros((10, 10))
        self.S_weighted = np.zeros((10, 10))
        self.p0: np.ndarray | None = None
        self.last_ok: EllipsoidFit | None = None
        self.n_reweightings = 0
        self.restarted_at = 0
        self._X = np.empty((256, 3))  # scaled points, grown by doubling
        self._w = np.empty(256)
        self._n = 0
        self._reweighted_at = 0  # point count at the last full reweighting
        self._cutoff = self.config.cutoff_mm / LENGTH_SCALE_MM

    @property
    def n_points(self) -> int:
        return self._n

    @property
    def weights(self) -> np.ndarray:
        return self._w[: self._n]

    def add(self, P: np.ndarray) -> None:
        """Accumulate finite points P (N, 3) mm, each weighted by the current fit."""
        if len(P) == 0:
            return
        if self.p0 is None:
            self.p0 = np.array(P[0], dtype=float)
        n = self._n + len(P)
        if n > len(self._X):
            size = max(n, 2 * len(self._X))
            self._X = np.concatenate([self._X[: self._n], np.empty((size - self._n, 3))])
            self._w = np.concatenate([self._w[: self._n], np.empty(size - self._n)])
        X = self._X[self._n : n]
        X[:] = (P - self.p0) / LENGTH_SCALE_MM
        v = np.zeros(10) if self.last_ok is None else self.last_ok.v
        _add_weighted_rows(self.S, self.S_weighted, X, v, self._cutoff, self._w[self._n : n])
        self._n = n

    def _reweight(self) -> None:
        """IRLS over all stored points, warm-started from the current fit."""
        X, w = self._X[: self._n], self._w[: self._n]
        M = design_rows(X)
        self._reweighted_at = self._n
        self.n_reweightings += 1
        for i in range(self.config.iterations):
            if self.last_ok is not None:
                w[:] = biweight(LENGTH_SCALE_MM * sampson_distance(self.last_ok.v, X), self.config.cutoff_mm)
            if i == 0 and np.count_nonzero(w) < self.config.min_inlier_fraction * self._n:
                w[:] = 1.0  # the warm start explains too few points: restart from the plain fit
                self.restarted_at = self._n
            self.S_weighted = (M * w[:, None]).T @ M
            result = fit_scatter(self.S_weighted, self.p0)
            if not result.ok:
                return
            self.last_ok = result

    def fit(self) -> EllipsoidFit:
        """Refit from S_w (after a full reweighting when one is due); keeps `last_ok` on
        failure."""
        if self.p0 is None:
            return EllipsoidFit("too_few_points")
        cfg = self.config
        if self._n - self._reweighted_at >= max(cfg.min_refit_points, cfg.refit_growth * self._reweighted_at):
            self._reweight()
        result = fit_scatter(self.S_weighted, self.p0)
        if result.ok:
            self.last_ok = result
        return result
