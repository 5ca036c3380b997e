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

from models.adaptive.coverage_kernels import add_points, covered_rows, inside_depth, nearest_and_worst
from models.shapes.validation import as_points, as_vector3


def fibonacci_directions(n: int) -> np.ndarray:
    """(n, 3) unit vectors spread evenly over the sphere (golden-angle spiral)."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    r = np.sqrt(1.0 - z * z)
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def inside_depth_upper_mm(shape, P: np.ndarray) -> np.ndarray:
    """(M,) an upper bound (mm) of how deep the points P (M, 3) lie inside `shape` (a
    models.Sphere or Ellipsoid; 0 for points outside): r_max (1 - k), k the scaled radius
    (a path of length d moves the scaled point by at least d / r_max). The NumPy formulas
    max(r - |P - c|, 0) and max(r_max (1 - |(P - c) R / radii|), 0), compiled but for the
    product by R (NumPy's, whose rounding a compiled sum does not reproduce). The radii go
    to the kernel as floats: the shape's arrays are read-only or not (a copied shape's),
    and each kind would be a compiled specialisation of its own."""
    D = P - shape.center
    if hasattr(shape, "radius"):
        return inside_depth(D, None, float(shape.radius))
    return inside_depth(D @ shape.rotation, tuple(shape.radii.tolist()), float(shape.radii.max()))


def band_chord(angle_rad: float) -> float:
    """The chord of an angle on the unit sphere, a hair long (rounding): the z band that
    holds every direction within the angle (nearest_and_worst's `chord`)."""
    return 2.0 * np.sin(angle_rad / 2.0) * (1.0 + 1e-12) + 1e-15


_FLOAT = np.dtype(np.float64)


class CoverageView:
    """An immutable snapshot of the covered directions: `angle_from_data_rad(Q)`, and,
    when made for a model shape, `local_misfit_mm(Q, angle)`: how far inside that shape
    the retina was measured near each direction (what the model gets wrong there)."""

    def __init__(self, center_W: np.ndarray, covered_dirs: np.ndarray, misfit_mm: np.ndarray | None = None):
        dirs = np.asarray(covered_dirs, dtype=float).reshape(-1, 3)
        order = np.argsort(dirs[:, 2], kind="stable")  # sorted by z: a query scans only its band
        self._hold(center_W, len(covered_dirs),
                   np.take(dirs, order, axis=0),  # a new contiguous array; ~2x faster than dirs[order]
                   None if misfit_mm is None else np.ascontiguousarray(np.asarray(misfit_mm, dtype=float)[order]))

    @classmethod
    def of_sorted(cls, center_W: np.ndarray, dirs: np.ndarray, misfit_mm: np.ndarray | None = None) -> CoverageView:
        """The view of contiguous float arrays already in a view's order, held as they are:
        the covered directions (M, 3) sorted by z (stably) and their misfits (M,) (or None)."""
        view = object.__new__(cls)
        view._hold(center_W, len(dirs), dirs, misfit_mm)
        return view

    def _hold(self, center_W: np.ndarray, n_covered: int, dirs: np.ndarray, misfit: np.ndarray | None) -> None:
        self.center_W, self.n_covered, self._dirs, self._misfit = center_W, n_covered, dirs, misfit

    def __deepcopy__(self, memo) -> CoverageView:
        return self  # immutable

    @property
    def sorted_directions(self) -> np.ndarray:
        """(N, 3) the covered unit directions, sorted by z ascending (read, don't change)."""
        return self._dirs

    @property
    def misfits_mm(self) -> np.ndarray | None:
        """(N,) the measured misfit (mm) of each covered direction, or None without a model."""
        return self._misfit

    def _directions(self, Q) -> np.ndarray:
        V = as_points(Q, "Q") - self.center_W
        return V / np.maximum(np.sqrt(np.einsum("ij,ij->i", V, V)), 1e-12)[:, None]

    def angle_from_data_rad(self, Q) -> np.ndarray:
        """(M,) angle (rad) between the direction of each point Q (M, 3) mm from the
        centre and the nearest covered direction (pi without data)."""
        V = self._directions(Q)
        if not self.n_covered:
            return np.full(len(V), np.pi)
        best, _ = nearest_and_worst(V, self._dirs, np.zeros(self.n_covered), 2.0)
        return np.arccos(np.clip(best, -1.0, 1.0))

    def local_misfit_mm(self, Q, angle_rad: float) -> np.ndarray:
        """(M,) the largest measured misfit (mm) over the covered directions within
        `angle_rad` of each point's direction (0 where none, or without a model)."""
        if not self.n_covered or self._misfit is None:
            return np.zeros(len(Q))
        return nearest_and_worst(self._directions(Q), self._dirs, self._misfit, np.cos(angle_rad),
                                  band_chord(angle_rad))[1]


class DirectionCoverage:
    """Covered directions from `center_W` (3,) mm, bins about `bin_deg` apart. `add(P)`
    marks the bins of measured points (the nearest Fibonacci direction, found by a
    compiled exact search); `view()` the current CoverageView (rebuilt only when the
    covered set grew by `rebuild_growth`, so calling it at 1 kHz is cheap)."""

    def __init__(self, center_W, bin_deg: float = 2.0, rebuild_growth: float = 0.02):
        if not (np.isfinite(bin_deg) and 0.2 <= bin_deg <= 30.0):
            raise ValueError(f"bin_deg must be in [0.2, 30] deg, got {bin_deg}")
        # a writeable copy whatever it came from (a frozen pose's read-only array, a fresh
        # one; deepcopy makes them writeable too): one compiled specialisation of the kernels
        # that take it, loaded before a run, not in a run's first packet
        self.center_W = as_vector3(center_W, "center_W").copy()
        n = int(np.ceil(4.0 * np.pi / np.radians(bin_deg) ** 2))
        self._dirs = fibonacci_directions(n)
        self._covered = np.zeros(n, dtype=bool)
        self._n_covered = 0
        self._inner = np.full((n, 3), np.nan)  # per bin: the measured point nearest the centre
        self._inner_r = np.full(n, np.inf)
        self._growth = float(rebuild_growth)
        self._view = CoverageView(self.center_W, np.zeros((0, 3)))
        self._view_shape = None

    def add(self, P) -> None:
        """Mark the bins of the measured points P (N, 3) mm (non-finite rows ignored)."""
        if not (type(P) is np.ndarray and P.dtype == _FLOAT and P.ndim == 2 and P.shape[1] == 3
                and P.flags.c_contiguous):  # else the kernel's own type already (the model's last_accepted)
            P = np.ascontiguousarray(as_points(P, "P", allow_nonfinite=True))
        self._n_covered += add_points(P, self.center_W, self._dirs, self._covered, self._inner, self._inner_r)

    def view(self, shape=None) -> CoverageView:
        """The current CoverageView; with a model `shape` (Sphere or Ellipsoid) it also
        holds each covered bin's misfit: how deep inside `shape` the innermost measured
        point of the bin lies (an upper bound, mm). Rebuilt when the covered set grew by
        `rebuild_growth` or the shape is another object (the model makes one per update:
        the misfit is of the shape the filter uses). Rebuilt on the kind only, a sphere
        refitted over a detachment kept the misfits of its predecessor: the detached eye's
        sphere-phase sphere shrank by 0.6 mm within 0.3 s of an adversarial scenario, the
        misfit next to the tip stayed 0.07 mm where the fresh one is 0.51 mm, and the tip
        came within 0.393 mm of the retina (seed 0, sphere-phase scenario 47)."""
        n = self._n_covered
        if n > self._view.n_covered * (1.0 + self._growth) or shape is not self._view_shape:
            dirs, inner = covered_rows(self._covered, self._dirs, self._inner, n)
            misfit = None if shape is None else inside_depth_upper_mm(shape, inner)
            self._view = CoverageView.of_sorted(self.center_W, dirs, misfit)
            self._view_shape = shape
        return self._view
