"""When to switch the eye model from the sphere to the ellipsoid.

A criterion is an immutable configuration with `initial_state()` (its per-model
memory) and `evaluate(snapshot, memory) -> ({name: (value, met)}, memory)`; the model
switches once, at the first update where every criterion it reports is met.
"""
from __future__ import annotations

from bisect import bisect_right
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from models.adaptive.extrapolation import drift_and_gap
from models.fit.ellipsoid_fit import LENGTH_SCALE_MM
from models.fit.quadric_residuals import residuals_since
from models.shapes.validation import check_count, check_positive


class FitSnapshot(NamedTuple):
    """What the adaptive model knows after one update (mm; relative changes unitless).

    `axis_change`: largest relative change of the sorted ellipsoid semi-axes since the
    previous update (NaN without a previous fit). `S`: the cumulative 10x10 scatter
    matrix in the fits' scaled coordinates (the model's own, which later updates change);
    `v_sf`, `v_ef`: the sphere's and ellipsoid's quadric coefficients in those
    coordinates (None if absent), arrays of this update's that are never written again;
    `sf` (center, radius) and `ef` (center, radii, rotation): the fits in mm (or None);
    `p0`: the origin of the scaled coordinates (mm); `fit_since`: the point count where
    the ellipsoid fit's history begins (0, or a robust fit's last restart); `robust`:
    whether the ellipsoid is a robust fit (models.fit.robust_fit) or the least-squares one.
    S[9, 9] is the (weighted) number of points in S: n_points for the least-squares fit,
    the share of points it predicted times n_points for a robust one (models.fit.robust_fit).
    """

    n_points: int
    scan_range_mm: float
    sf_residual_mm: float
    ef_residual_mm: float
    axis_change: float
    S: np.ndarray
    v_sf: np.ndarray | None
    v_ef: np.ndarray | None
    sf: tuple | None = None
    ef: tuple | None = None
    p0: np.ndarray | None = None
    fit_since: int = 0
    robust: bool = False


@dataclass(frozen=True)
class PaperCriteria:
    """The paper's three criteria, all of which must hold to switch (defaults: the paper).

    - scan range (largest distance between measured points) > `min_scan_range_mm`;
    - ellipsoid-fit residual < sphere-fit residual;
    - relative semi-axis change < `max_axis_change` (0.03 %) for more than
      `min_stable_updates` (15) consecutive updates.
    """

    min_scan_range_mm: float = 20.0
    max_axis_change: float = 3e-4
    min_stable_updates: int = 15

    names = ("scan_range", "residual", "temporal")
    reversible = False  # the paper switches once

    def __post_init__(self):
        check_positive(self, "min_scan_range_mm", allow_zero=True)
        check_positive(self, "max_axis_change")
        check_count(self, "min_stable_updates")

    def initial_state(self) -> int:
        """Per-model memory: the count of consecutive stable updates."""
        return 0

    def evaluate(self, snap: FitSnapshot, stable: int):
        """({criterion: (value, met)}, new memory) for this update."""
        stable = stable + 1 if snap.axis_change < self.max_axis_change else 0
        return {
            "scan_range": (snap.scan_range_mm, snap.scan_range_mm > self.min_scan_range_mm),
            "residual": (
                snap.ef_residual_mm - snap.sf_residual_mm,
                bool(snap.ef_residual_mm < snap.sf_residual_mm),
            ),
            "temporal": (float(stable), stable > self.min_stable_updates),
        }, stable


class _PredictiveMemory:
    """Checkpoints (points so far, scatter matrix, sphere and ellipsoid quadrics) and the
    last evaluation of a PredictiveCriteria."""

    def __init__(self):
        self.n: list[int] = []
        self.S: list[np.ndarray] = []
        self.v_sf: list[np.ndarray | None] = []
        self.v_ef: list[np.ndarray | None] = []
        self.last = {name: (np.nan, False) for name in ("fit", "convergence", "prediction")}
        self.stable = 0
        self.misfit = 0  # consecutive checkpoints at which the ellipsoid did not explain the data

    def __deepcopy__(self, memo) -> _PredictiveMemory:
        """An independent copy that shares the checkpoints: a checkpoint's arrays are never
        written once appended (PredictiveCriteria.evaluate appends copies), so the copy
        appends to lists of its own; copying the arrays was most of a spiral-built
        model's copy, once per scenario of a campaign."""
        new = object.__new__(type(self))
        memo[id(self)] = new
        new.n, new.S, new.v_sf, new.v_ef = list(self.n), list(self.S), list(self.v_sf), list(self.v_ef)
        new.last, new.stable, new.misfit = dict(self.last), self.stable, self.misfit
        return new


@dataclass(frozen=True)
class PredictiveCriteria:
    """Switch when the ellipsoid is known to be the better model of the whole retina,
    not only of the patch scanned so far (our criterion; the paper's stays available).

    The model must answer for retina the fibre has not seen, so every condition is
    about extrapolation. At each checkpoint (every `check_every` points):
    - scan range > `min_scan_range_mm` (too small a patch says nothing about shape);
    - fit: the least-squares ellipsoid's residual < `fit_factor` x `noise_sd_mm`, i.e.
      it explains the data to the noise level (a staphyloma or a detachment does not
      look like an ellipsoid once scanned across, and then its extrapolation cannot be
      trusted); a robust ellipsoid leaves such patches out by design, and must instead
      have predicted at least `min_explained_fraction` of the newest `window_fraction`
      of the points (S[9, 9]'s share of them), so that it has not locked onto a
      pathology the scan is leaving;
    - convergence: over the retina (anterior `crop_mm` excluded), the ellipsoid has
      moved since the fit of `lag_fraction` of the points (counted from `fit_since`,
      where a robust fit's history begins anew) by less than
      `convergence_factor` x its mean distance from the sphere: the two models disagree
      by more than the ellipsoid is still changing, so the sphere is the one that is
      off (the ellipsoid fitted to a small patch is biased by the noise, and that bias
      shows as drift long before it shows in any residual);
    - prediction: the fits made when `lag_fraction` of the points were in (counted as
      for convergence) predict the newest `window_fraction` of the points, which they
      never saw, and the ellipsoid's RMS error is the smaller (prequential validation,
      from windowed scatter matrices).
    The model switches to the ellipsoid when all hold for `min_stable_checks`
    consecutive checkpoints, and back to the sphere when the fit condition fails for as
    many. Every check is O(1) in the number of points.
    """

    noise_sd_mm: float = 0.020
    fit_factor: float = 1.5
    convergence_factor: float = 0.45
    crop_mm: float = 5.0
    min_scan_range_mm: float = 10.0
    lag_fraction: float = 0.8
    window_fraction: float = 0.1
    check_every: int = 25
    min_stable_checks: int = 6
    min_explained_fraction: float = 0.5

    names = ("scan_range", "fit", "convergence", "prediction", "stable")
    reversible = True

    def __post_init__(self):
        check_positive(self, "noise_sd_mm", "fit_factor", "convergence_factor")
        check_positive(self, "min_scan_range_mm", "crop_mm", allow_zero=True)
        for name in ("lag_fraction", "window_fraction", "min_explained_fraction"):
            v = getattr(self, name)
            if not (np.isfinite(v) and 0.0 < v < 1.0):
                raise ValueError(f"{name} must be in (0, 1), got {v}")
        check_count(self, "check_every", minimum=1)
        check_count(self, "min_stable_checks")

    def initial_state(self) -> _PredictiveMemory:
        return _PredictiveMemory()

    def _convergence(self, snap: FitSnapshot, v_ef_old: np.ndarray):
        """(ellipsoid drift / sphere-ellipsoid distance over the retina, met)."""
        c_ef, r_ef, R_ef = snap.ef
        drift, gap, k = drift_and_gap(c_ef, r_ef, R_ef, snap.p0, LENGTH_SCALE_MM, snap.S, self.crop_mm, v_ef_old,
                                      *snap.sf)
        if not k:  # an early, tiny ellipsoid lies wholly in the cropped front: not converged
            return np.inf, False
        ratio = drift / gap if gap > 0 else np.inf
        return ratio, bool(ratio < self.convergence_factor)

    def _checkpoint(self, snap: FitSnapshot, mem: _PredictiveMemory) -> None:
        mem.n.append(snap.n_points)
        mem.S.append(snap.S.copy())
        mem.v_sf.append(snap.v_sf)  # never written again (FitSnapshot): kept as they are
        mem.v_ef.append(snap.v_ef)
        if snap.v_ef is None or snap.sf is None:
            mem.last = {name: (np.nan, False) for name in mem.last}
            return
        # the last checkpoints with at most the points before the newest window, and before the lag (-1: none)
        w = bisect_right(mem.n, (1.0 - self.window_fraction) * snap.n_points) - 1
        if not snap.robust:
            fit_ratio = snap.ef_residual_mm / self.noise_sd_mm
            mem.last["fit"] = (fit_ratio, bool(fit_ratio < self.fit_factor))
        elif 0 <= w < len(mem.n) - 1:
            explained = float(snap.S[9, 9] - mem.S[w][9, 9]) / (snap.n_points - mem.n[w])
            mem.last["fit"] = (explained, bool(explained >= self.min_explained_fraction))
        else:
            mem.last["fit"] = (np.nan, False)
        j = bisect_right(mem.n, snap.fit_since + self.lag_fraction * (snap.n_points - snap.fit_since)) - 1
        old_ef = mem.v_ef[j] if j >= 0 else None
        mem.last["convergence"] = (np.nan, False) if old_ef is None else self._convergence(snap, old_ef)
        gain, better = np.nan, False
        if old_ef is not None and 0 <= w < len(mem.n) - 1 and mem.v_sf[j] is not None:
            # RMS errors (mm) of the old sphere and ellipsoid over the points since checkpoint w
            e_sf, e_ef = residuals_since(snap.S, mem.S[w], mem.v_sf[j], old_ef)
            e_sf, e_ef = LENGTH_SCALE_MM * e_sf, LENGTH_SCALE_MM * e_ef
            gain, better = e_sf - e_ef, e_ef < e_sf
        mem.last["prediction"] = (gain, better)

    def checkpoint_due(self, n_points: int, mem: _PredictiveMemory) -> bool:
        """Whether an update that brings the model to n_points is a checkpoint."""
        return n_points >= (mem.n[-1] if mem.n else 0) + self.check_every

    def evaluate(self, snap: FitSnapshot, mem: _PredictiveMemory):
        """({criterion: (value, met)}, memory) for this update."""
        range_ok = snap.scan_range_mm > self.min_scan_range_mm
        if self.checkpoint_due(snap.n_points, mem):
            self._checkpoint(snap, mem)
            last = mem.last
            all_ok = range_ok and all(met for _, met in last.values())
            mem.stable = mem.stable + 1 if all_ok else 0
            mem.misfit = 0 if last["fit"][1] else mem.misfit + 1
        return {
            "scan_range": (snap.scan_range_mm, range_ok),
            **mem.last,
            "stable": (float(mem.stable), mem.stable >= self.min_stable_checks),
        }, mem

    def wants_sphere(self, mem: _PredictiveMemory) -> bool:
        """True when the ellipsoid has failed the fit condition long enough to drop it."""
        return mem.misfit >= max(self.min_stable_checks, 1)


CRITERIA = {"paper": PaperCriteria, "predictive": PredictiveCriteria}
