"""Ellipsoid-specific least squares (Li & Griffiths 2004, k = 4), batch and incremental.

The fit works on the 10x10 scatter matrix S = sum m(p) m(p)^T of the design rows
m = [x^2, y^2, z^2, 2yz, 2xz, 2xy, 2x, 2y, 2z, 1], taken in coordinates centred on
a reference point and divided by a length scale, so that the normal equations stay
well conditioned whatever frame the points come in (the robot base is ~300 mm
away). S is a sum, so it grows by one rank-1 update per point: the incremental
fit costs O(1) per point whatever N.
"""
from __future__ import annotations

import numpy as np

from models.fit.quadric_kernels import FIT_STATUS, add_design_rows, fit_ellipsoid_scatter, spread_check_due
from models.fit.quadric_residuals import taubin_residuals
from models.shapes.ellipsoid import Ellipsoid
from models.shapes.validation import as_points

LENGTH_SCALE_MM = 10.0  # scaled coordinates are O(1) for an eye


class EllipsoidFit:
    """Outcome of one ellipsoid fit.

    `status` is "ok" or the reason of failure ("too_few_points", "collinear",
    "coplanar", "not_ellipsoid"), `ok` whether it is "ok"; on success `center` (3,) mm,
    `radii` (3,) mm (descending) and `rotation` (3, 3) describe it, `v` (10,) holds the
    quadric in scaled coordinates, and `ellipsoid` builds the Ellipsoid on first use and
    keeps it (the per-update hot path only needs the arrays; a successful fit's arrays
    come from the fit kernel, so Ellipsoid.of_fit takes them without checking them again).
    """

    __slots__ = ("status", "ok", "center", "radii", "rotation", "v", "_ellipsoid")

    def __init__(self, status, center=None, radii=None, rotation=None, v=None):
        self.status = status
        self.ok = status == "ok"
        self.center, self.radii, self.rotation, self.v = center, radii, rotation, v
        self._ellipsoid = None

    @property
    def ellipsoid(self) -> Ellipsoid | None:
        if self._ellipsoid is None and self.ok:
            self._ellipsoid = Ellipsoid.of_fit(self.center, self.radii, self.rotation)
        return self._ellipsoid


def taubin_residual(S: np.ndarray, v: np.ndarray):
    """RMS point-to-surface distance (scaled units) of quadric v (10,) -- or of each row
    of v (k, 10) -- over the points of S, in Taubin's first-order form
    sqrt(sum Q^2 / sum |grad Q|^2), from the moments alone: O(1) whatever the number of
    points (models.fit.quadric_residuals.taubin_residuals)."""
    if v.ndim == 2:
        return taubin_residuals(S, v)
    return float(taubin_residuals(S, v[None])[0])


def fit_scatter(S: np.ndarray, p0: np.ndarray, scale: float = LENGTH_SCALE_MM, check_spread: bool = True) -> EllipsoidFit:
    """Fit an ellipsoid to the points summarised by scatter matrix S (see module doc).
    `check_spread=False` skips the collinear/coplanar test (for a caller that knows the
    cloud is already spread in 3-D); too few points are always refused."""
    return fit_of(fit_ellipsoid_scatter(S, p0, scale, check_spread))


def fit_of(result) -> EllipsoidFit:
    """The EllipsoidFit of fit_ellipsoid_scatter's (code, v, centre, semi-axes, rotation)."""
    code, v, center, radii, rotation = result
    if code:
        return EllipsoidFit(FIT_STATUS[code])
    return EllipsoidFit("ok", center, radii, rotation, v=v)


def fit_ellipsoid(P) -> Ellipsoid:
    """Ellipsoid-specific least-squares fit to points P (N >= 9, mm, any frame).

    Returns an Ellipsoid (centre, semi-axes, rotation) in the frame of P. Raises
    ValueError naming the reason when the points cannot define an ellipsoid (fewer
    than 9, collinear, coplanar, or a best quadric that is not an ellipsoid).
    """
    P = as_points(P, "P")
    p0 = P.mean(axis=0) if len(P) else np.zeros(3)
    S = np.zeros((10, 10))
    add_design_rows(S, P, p0, LENGTH_SCALE_MM)  # the scatter matrix as the incremental fit builds it
    fit = fit_scatter(S, p0)
    if not fit.ok:
        raise ValueError(f"fit_ellipsoid: cannot fit an ellipsoid to {len(P)} points: {fit.status}")
    return fit.ellipsoid


class IncrementalEllipsoidFit:
    """Ellipsoid fit that absorbs points one at a time (O(1) each) and refits on demand.

    The reference point is the first point received; coordinates are scaled by
    LENGTH_SCALE_MM. `fit()` returns the new EllipsoidFit; when it fails, `last_ok`
    still holds the previous good fit (graceful fall-back) and `fit().status` says why.
    """

    SPREAD_RECHECK = 64  # points between re-checks of a cloud already found spread in 3-D
    restarted_at = 0  # the fit's history begins with the first point (cf. models.fit.robust_fit)

    def __init__(self):
        self.S = np.zeros((10, 10))
        self._n = 0  # points in S (its [9, 9] entry, kept as an int)
        self.p0: np.ndarray | None = None
        self.last_ok: EllipsoidFit | None = None
        self.spread_checked_at = 0  # the point count at the last passed spread test (0: none)

    @property
    def n_points(self) -> int:
        return self._n

    def add(self, P: np.ndarray) -> None:
        """Accumulate finite points P (N, 3) or (3,) mm; ValueError on a non-finite one (the
        adaptive model filters them out before)."""
        P = as_points(P, "P")
        if len(P) == 0:
            return
        if self.p0 is None:
            self.p0 = np.array(P[0], dtype=float)
        add_design_rows(self.S, P, self.p0, LENGTH_SCALE_MM)
        self._n += len(P)

    def fit(self) -> EllipsoidFit:
        """Refit from all points so far; keeps `last_ok` on failure."""
        if self.p0 is None:
            return EllipsoidFit("too_few_points")
        check = self.spread_check_due(self.n_points)
        return self.record(fit_scatter(self.S, self.p0, check_spread=check), check)

    def spread_check_due(self, n: int) -> bool:
        """Whether the fit of n points must run the collinear/coplanar test. Adding points
        only widens a cloud's scatter about its mean, so once spread in 3-D it stays so;
        the ratio test is still repeated every SPREAD_RECHECK points."""
        return spread_check_due(self.spread_checked_at, n, self.SPREAD_RECHECK)

    def record(self, result: EllipsoidFit, checked: bool, took: int = 0) -> EllipsoidFit:
        """Take in the fit `result` of all points so far (`checked`: with the spread test):
        `last_ok` and the spread test's schedule; returns the result. For a caller that
        ran the fit kernel itself (the per-A-scan update, models.adaptive.model), which has also
        added `took` points to S itself (add_design_rows about p0 with LENGTH_SCALE_MM:
        models.adaptive.update_kernel.packet_update)."""
        self._n += took
        if checked:
            self.spread_checked_at = self._n if result.status not in ("collinear", "coplanar", "too_few_points") else 0
        if result.ok:
            self.last_ok = result
        return result
