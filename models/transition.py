"""When to switch the eye model from the sphere to the ellipsoid."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FitSnapshot:
    """What the adaptive model knows after one update (mm; relative changes unitless).

    `axis_change` is the largest relative change of the sorted ellipsoid semi-axes since
    the previous update (NaN when there is no previous fit); `stable_updates` counts the
    consecutive updates with `axis_change` below the criterion's threshold.
    """

    n_points: int
    scan_range_mm: float
    sf_residual_mm: float
    ef_residual_mm: float
    axis_change: float


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
        if not (np.isfinite(self.min_scan_range_mm) and self.min_scan_range_mm >= 0):
            raise ValueError(f"min_scan_range_mm must be finite and >= 0, got {self.min_scan_range_mm}")
        if not (np.isfinite(self.max_axis_change) and self.max_axis_change > 0):
            raise ValueError(f"max_axis_change must be finite and > 0, got {self.max_axis_change}")
        if int(self.min_stable_updates) != self.min_stable_updates or self.min_stable_updates < 0:
            raise ValueError(f"min_stable_updates must be an integer >= 0, got {self.min_stable_updates}")

    def initial_state(self) -> int:
        """Per-model memory: the count of consecutive stable updates."""
        return 0

    def evaluate(self, snap: FitSnapshot, stable: int) -> tuple[dict[str, tuple[float, bool]], int]:
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
