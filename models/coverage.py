"""Where the eye model has data: the directions, seen from the eye centre, in which the
fiber has measured the retina.

A fit is only as good as its data: an ellipsoid fitted to a posterior cap extrapolates
well on a regular eye and millimetres off on a pointed one, and nothing in the fit's
residuals tells the two apart. So the safety filter trusts the model near measured
directions and, elsewhere, also keeps the conservative prior. Directions are binned on a
Fibonacci sphere (about `bin_deg` apart); a direction is covered once a measured point
falls in its bin. Units: mm, rad (degrees where named); frame W.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from models._validation import as_points, as_vector3


def fibonacci_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (golden-angle spiral)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


class CoverageView:
    """An immutable snapshot of the covered directions: `angle_from_data_rad(Q)`."""

    def __init__(self, center_W: np.ndarray, covered_dirs: np.ndarray):
        self.center_W = center_W
        self.n_covered = len(covered_dirs)
        self._tree = cKDTree(covered_dirs) if len(covered_dirs) else None

    def __deepcopy__(self, memo) -> CoverageView:
        return self  # immutable

    def angle_from_data_rad(self, Q) -> np.ndarray:
        """(M,) angle (rad) between the direction of each point Q (M, 3) mm from the
        centre and the nearest covered direction (pi without data)."""
        V = as_points(Q, "Q") - self.center_W
        V = V / np.maximum(np.linalg.norm(V, axis=1, keepdims=True), 1e-12)
        if self._tree is None:
            return np.full(len(V), np.pi)
        chord, _ = self._tree.query(V)
        return 2.0 * np.arcsin(np.minimum(chord / 2.0, 1.0))


class DirectionCoverage:
    """Covered directions from `center_W` (3,) mm, bins about `bin_deg` apart. `add(P)`
    marks the bins of measured points; `view()` the current CoverageView (rebuilt only
    when the covered set grew by `rebuild_growth`, so calling it at 1 kHz is cheap)."""

    def __init__(self, center_W, bin_deg: float = 2.0, rebuild_growth: float = 0.02):
        if not (np.isfinite(bin_deg) and 0.2 <= bin_deg <= 30.0):
            raise ValueError(f"bin_deg must be in [0.2, 30] deg, got {bin_deg}")
        self.center_W = as_vector3(center_W, "center_W")
        n = int(np.ceil(4.0 * np.pi / np.radians(bin_deg) ** 2))
        self._dirs = fibonacci_directions(n)
        self._bins = cKDTree(self._dirs)
        self._covered = np.zeros(n, dtype=bool)
        self._n_covered = 0
        self._growth = float(rebuild_growth)
        self._view = CoverageView(self.center_W, np.zeros((0, 3)))

    def add(self, P) -> None:
        """Mark the bins of the measured points P (N, 3) mm (non-finite rows ignored)."""
        P = as_points(P, "P", allow_nonfinite=True)
        P = P[np.isfinite(P).all(axis=1)]
        if not len(P):
            return
        V = P - self.center_W
        V /= np.maximum(np.linalg.norm(V, axis=1, keepdims=True), 1e-12)
        _, idx = self._bins.query(V)
        self._covered[idx] = True

    def view(self) -> CoverageView:
        n = int(self._covered.sum())
        if n > self._view.n_covered * (1.0 + self._growth):
            self._view = CoverageView(self.center_W, self._dirs[self._covered])
        return self._view
