"""Robust incremental ellipsoid fit: the healthy globe of an eye with a local pathology.

A detachment or a staphyloma is a patch of retina that no quadric follows; the plain
least-squares fit bends towards it and then extrapolates badly to the retina the fibre
has not seen. This fit down-weights such patches with Tukey's biweight on each point's
first-order (Sampson) distance d from the current fit,

    w = (1 - (d / c)^2)^2 for |d| < c, else 0,   c = `tukey_factor` x `noise_sd_mm`,

so that points within a few noise SDs of the ellipsoid count almost fully and points on a
pathology (millimetres off) not at all: the fit minimises v^T S_w v over the weighted
scatter matrix S_w = sum w m m^T (models.fit.ellipsoid_fit) by iteratively reweighted least
squares (IRLS). The weight (biweight_one), its loss (tukey_rho) and the cut-off
(RobustFitConfig.cutoff_mm) are defined here once; models.fit.streaming_robust's fit
weighs its points with the same functions.

Cost: a new point gets its weight from the current fit and joins S_w (O(1), the compiled
Sampson distance and weighted design-row accumulation of models.fit.quadric_residuals
and models.fit.quadric_kernels); all weights are recomputed from the stored points,
`iterations` IRLS steps warm-started from the current fit, whenever the point count has grown by `refit_growth`
since the last reweighting (and by at least `min_refit_points`). A reweighting costs O(N)
but they come geometrically rarer, so the amortised cost per point is O(1): about
iterations x (1 + 1 / refit_growth) design rows. Memory: the points, N x 3 floats.
Coordinates as in models.fit.ellipsoid_fit: origin at the first point, lengths divided by
LENGTH_SCALE_MM.

What the transition criteria see (models.adaptive.transition): `S` is the scatter matrix of the
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

from models.buffers import grown
from models.fit.ellipsoid_fit import LENGTH_SCALE_MM, EllipsoidFit, fit_scatter
from models.fit.quadric_kernels import add_weighted_design_rows
from models.fit.quadric_residuals import sampson_distances
from models.shapes.validation import check_count, check_positive

_ORIGIN = np.zeros(3)


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


@njit(cache=True, inline="always")
def _inside_share(d, cutoff):
    """1 - (d / c)^2 for |d| < c, else 0: the cut-off's rule, which the weight and the loss share."""
    u = min(abs(d) / cutoff, 1.0)
    return 1.0 - u * u


@njit(cache=True, inline="always")
def biweight_one(d, cutoff):
    """Tukey's biweight (1 - (d / c)^2)^2 of the distance d, 0 beyond the cut-off c (c in d's units)."""
    t = _inside_share(d, cutoff)
    return t * t


@njit(cache=True, inline="always")
def tukey_rho(d, cutoff):
    """Tukey's rho of the distance d with the cut-off c: (c^2 / 6) (1 - (1 - (d / c)^2)^3),
    c^2 / 6 beyond c (the loss whose IRLS weight is biweight_one; units of d^2)."""
    t = _inside_share(d, cutoff)
    return cutoff * cutoff / 6.0 * (1.0 - t * t * t)


@njit(cache=True)
def biweight(d_mm, cutoff_mm):
    """(N,) biweight_one of the distances d_mm (N,) mm with the cut-off cutoff_mm (mm)."""
    out = np.empty(d_mm.shape[0])
    for k in range(d_mm.shape[0]):
        out[k] = biweight_one(d_mm[k], cutoff_mm)
    return out


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
            self._X, self._w = grown(self._n, n, self._X, self._w)
        X, w = self._X[self._n : n], self._w[self._n : n]
        X[:] = (P - self.p0) / LENGTH_SCALE_MM
        w[:] = 1.0 if self.last_ok is None else self._weights(X)
        dS = np.zeros((10, 10))
        add_weighted_design_rows(dS, X, _ORIGIN, 1.0, w)  # X is already scaled
        self.S += dS
        self.S_weighted += dS
        self._n = n

    def _weights(self, X: np.ndarray) -> np.ndarray:
        """Biweights of scaled points X (N, 3) from the current fit's Sampson distances."""
        return biweight(LENGTH_SCALE_MM * sampson_distances(self.last_ok.v, X), self.config.cutoff_mm)

    def _reweight(self) -> EllipsoidFit | None:
        """IRLS over all stored points, warm-started from the current fit; the last pass's
        fit of S_w (None without a pass)."""
        X, w = self._X[: self._n], self._w[: self._n]
        self._reweighted_at = self._n
        self.n_reweightings += 1
        result = None
        for i in range(self.config.iterations):
            if self.last_ok is not None:
                w[:] = self._weights(X)
            if i == 0 and np.count_nonzero(w) < self.config.min_inlier_fraction * self._n:
                w[:] = 1.0  # the warm start explains too few points: restart from the plain fit
                self.restarted_at = self._n
            self.S_weighted = np.zeros((10, 10))
            add_weighted_design_rows(self.S_weighted, X, _ORIGIN, 1.0, w)  # X is already scaled
            result = fit_scatter(self.S_weighted, self.p0)
            if not result.ok:
                return result
            self.last_ok = result
        return result

    def fit(self) -> EllipsoidFit:
        """Refit from S_w (after a full reweighting when one is due); keeps `last_ok` on
        failure."""
        if self.p0 is None:
            return EllipsoidFit("too_few_points")
        cfg = self.config
        result = None  # a reweighting's last pass has fitted S_w already
        if self._n - self._reweighted_at >= max(cfg.min_refit_points, cfg.refit_growth * self._reweighted_at):
            result = self._reweight()
        if result is None:
            result = fit_scatter(self.S_weighted, self.p0)
        if result.ok:
            self.last_ok = result
        return result
