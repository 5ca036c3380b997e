"""When to switch the eye model from the sphere to the ellipsoid.

A criterion is an immutable configuration with `initial_state()` (its per-model
memory) and `evaluate(snapshot, memory) -> ({name: (value, met)}, memory)`; the model
switches once, at the first update where every criterion it reports is met.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.ellipsoid_fit import LENGTH_SCALE_MM, taubin_residual


@dataclass(frozen=True, eq=False)
class FitSnapshot:
    """What the adaptive model knows after one update (mm; relative changes unitless).

    `axis_change`: largest relative change of the sorted ellipsoid semi-axes since the
    previous update (NaN without a previous fit). `S`: the cumulative 10x10 scatter
    matrix in the fits' scaled coordinates (read-only view); `v_sf`, `v_ef`: the
    sphere's and ellipsoid's quadric coefficients in those coordinates (None if absent).
    """

    n_points: int
    scan_range_mm: float
    sf_residual_mm: float
    ef_residual_mm: float
    axis_change: float
    S: np.ndarray
    v_sf: np.ndarray | None
    v_ef: np.ndarray | None


def _check_positive(name: str, value: float, allow_zero: bool = False) -> None:
    ok = np.isfinite(value) and (value >= 0 if allow_zero else value > 0)
    if not ok:
        raise ValueError(f"{name} must be finite and {'>=' if allow_zero else '>'} 0, got {value}")


def _check_count(name: str, value) -> None:
    if int(value) != value or value < 0:
        raise ValueError(f"{name} must be an integer >= 0, got {value}")


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

    def __post_init__(self):
        _check_positive("min_scan_range_mm", self.min_scan_range_mm, allow_zero=True)
        _check_positive("max_axis_change", self.max_axis_change)
        _check_count("min_stable_updates", self.min_stable_updates)

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
        self.last = {"fit": (np.nan, False), "prediction": (np.nan, False)}
        self.stable = 0


@dataclass(frozen=True)
class PredictiveCriteria:
    """Switch when the ellipsoid explains the data to the noise level and predicts new
    retina better than the sphere (our criterion; the paper's stays available).

    The retina the model must answer for is mostly retina the fiber has not seen yet,
    so the criterion judges each model by what it predicted: at every checkpoint
    (each `check_every` points) the fits made when only `lag_fraction` of the current
    points were in are scored on the newest `window_fraction` of the points, which
    they never saw (prequential validation). All of these must hold for
    `min_stable_checks` consecutive checkpoints:
    - scan range > `min_scan_range_mm` (too small a patch says nothing about shape);
    - fit: ellipsoid residual < `fit_factor` x `noise_sd_mm` (the ellipsoid explains
      the data; a shape it cannot explain, such as a staphyloma, makes its
      extrapolation unreliable, however well it predicts the next ring);
    - prediction: the earlier ellipsoid's RMS error on the new points < the earlier
      sphere's.
    Errors are Taubin's first-order distances from windowed scatter matrices (S now
    minus S at the window start): O(1) per checkpoint, whatever the number of points.
    """

    noise_sd_mm: float = 0.020
    fit_factor: float = 1.5
    min_scan_range_mm: float = 10.0
    lag_fraction: float = 0.8
    window_fraction: float = 0.1
    check_every: int = 25
    min_stable_checks: int = 3

    names = ("scan_range", "fit", "prediction", "stable")

    def __post_init__(self):
        _check_positive("noise_sd_mm", self.noise_sd_mm)
        _check_positive("fit_factor", self.fit_factor)
        _check_positive("min_scan_range_mm", self.min_scan_range_mm, allow_zero=True)
        for name in ("lag_fraction", "window_fraction"):
            v = getattr(self, name)
            if not (np.isfinite(v) and 0.0 < v < 1.0):
                raise ValueError(f"{name} must be in (0, 1), got {v}")
        _check_count("check_every", self.check_every)
        _check_count("min_stable_checks", self.min_stable_checks)
        if self.check_every < 1:
            raise ValueError(f"check_every must be >= 1, got {self.check_every}")

    def initial_state(self) -> _PredictiveMemory:
        return _PredictiveMemory()

    @staticmethod
    def _at_most(mem: _PredictiveMemory, n: float) -> int | None:
        """Index of the last checkpoint with at most n points, or None."""
        i = int(np.searchsorted(mem.n, n, side="right")) - 1
        return i if i >= 0 else None

    def _checkpoint(self, snap: FitSnapshot, mem: _PredictiveMemory) -> None:
        mem.n.append(snap.n_points)
        mem.S.append(snap.S.copy())
        mem.v_sf.append(None if snap.v_sf is None else snap.v_sf.copy())
        mem.v_ef.append(None if snap.v_ef is None else snap.v_ef.copy())
        fit_ratio = snap.ef_residual_mm / self.noise_sd_mm
        mem.last["fit"] = (fit_ratio, bool(fit_ratio < self.fit_factor))
        j = self._at_most(mem, self.lag_fraction * snap.n_points)
        w = self._at_most(mem, (1.0 - self.window_fraction) * snap.n_points)
        gain, better = np.nan, False
        if j is not None and w is not None and w < len(mem.n) - 1 and mem.v_sf[j] is not None and mem.v_ef[j] is not None:
            S_new = snap.S - mem.S[w]
            e_sf = LENGTH_SCALE_MM * taubin_residual(S_new, mem.v_sf[j])
            e_ef = LENGTH_SCALE_MM * taubin_residual(S_new, mem.v_ef[j])
            gain, better = e_sf - e_ef, bool(e_ef < e_sf)
        mem.last["prediction"] = (gain, better)

    def evaluate(self, snap: FitSnapshot, mem: _PredictiveMemory):
        """({criterion: (value, met)}, memory) for this update."""
        at_checkpoint = snap.n_points >= (mem.n[-1] if mem.n else 0) + self.check_every
        if at_checkpoint:
            self._checkpoint(snap, mem)
        range_ok = snap.scan_range_mm > self.min_scan_range_mm
        if at_checkpoint:
            all_ok = range_ok and mem.last["fit"][1] and mem.last["prediction"][1]
            mem.stable = mem.stable + 1 if all_ok else 0
        return {
            "scan_range": (snap.scan_range_mm, range_ok),
            "fit": mem.last["fit"],
            "prediction": mem.last["prediction"],
            "stable": (float(mem.stable), mem.stable >= self.min_stable_checks),
        }, mem


CRITERIA = {"paper": PaperCriteria, "predictive": PredictiveCriteria}
