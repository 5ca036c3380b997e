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
from scipy.linalg import lapack

from models._validation import as_points
from models.ellipsoid import Ellipsoid

MIN_POINTS = 9
LENGTH_SCALE_MM = 10.0  # scaled coordinates are O(1) for an eye
_PLANARITY_TOL = 1e-10  # smallest / largest point-cloud variance below which data is flat

# v1^T C1 v1 = 4 J - I^2 for v1 = (a, b, c, f, g, h) (k = 4).
_C1 = np.zeros((6, 6))
_C1[:3, :3] = 1.0
np.fill_diagonal(_C1[:3, :3], -1.0)
_C1[3:, 3:] = -4.0 * np.eye(3)
_C1_INV = np.linalg.inv(_C1)


def design_rows(X: np.ndarray) -> np.ndarray:
    """(N, 10) design rows m(x) for scaled, centred points X (N, 3)."""
    x, y, z = X.T
    return np.column_stack(
        [x * x, y * y, z * z, 2 * y * z, 2 * x * z, 2 * x * y, 2 * x, 2 * y, 2 * z, np.ones(len(X))]
    )


class EllipsoidFit:
    """Outcome of one ellipsoid fit.

    `status` is "ok" or the reason of failure ("too_few_points", "collinear",
    "coplanar", "not_ellipsoid"); on success `center` (3,) mm, `radii` (3,) mm
    (descending) and `rotation` (3, 3) describe it, `v` (10,) holds the quadric in
    scaled coordinates, and `ellipsoid` builds the validated Ellipsoid on first use
    (the per-update hot path only needs the arrays).
    """

    __slots__ = ("status", "center", "radii", "rotation", "v", "_ellipsoid")

    def __init__(self, status, center=None, radii=None, rotation=None, v=None):
        self.status = status
        self.center, self.radii, self.rotation, self.v = center, radii, rotation, v
        self._ellipsoid = None

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def ellipsoid(self) -> Ellipsoid | None:
        if self._ellipsoid is None and self.ok:
            self._ellipsoid = Ellipsoid(self.center, self.radii, self.rotation)
        return self._ellipsoid


def degeneracy(S: np.ndarray) -> str | None:
    """The reason the points behind scatter matrix S cannot define an ellipsoid, or None."""
    n = S[9, 9]
    if n < MIN_POINTS:
        return "too_few_points"
    mean = S[6:9, 9] / (2.0 * n)
    cov = S[6:9, 6:9] / (4.0 * n) - np.outer(mean, mean)
    w, _, info = lapack.dsyevd(cov, compute_v=0)  # direct LAPACK: small-matrix overhead matters here
    if info != 0 or w[-1] <= 0.0 or w[1] <= _PLANARITY_TOL * w[-1]:
        return "collinear"
    if w[0] <= _PLANARITY_TOL * w[-1]:
        return "coplanar"
    return None


def solve_scatter(S: np.ndarray) -> np.ndarray | None:
    """Quadric coefficients v (10,) minimising v^T S v subject to 4J - I^2 = 1, or None
    when no ellipsoid solution exists (no generalised eigenvector with v^T C1 v > 0)."""
    S11, S12, S22 = S[:6, :6], S[:6, 6:], S[6:, 6:]
    _, X, info = lapack.dposv(S22, S12.T)  # S22 is positive definite unless the data is flat
    if info != 0:
        raise np.linalg.LinAlgError("scatter block S22 is singular (flat data)")
    wr, wi, _, V, info = lapack.dgeev(_C1_INV @ (S11 - S12 @ X), compute_vl=0)
    if info != 0:
        return None
    # M v = lambda C1 v, so v^T M v / v^T C1 v = lambda: among the real eigenvectors
    # that satisfy the ellipsoid constraint (v^T C1 v > 0; dgeev's columns have unit
    # norm), the least-squares one has the smallest lambda (>= 0: M is semi-definite).
    c = (V * (_C1 @ V)).sum(axis=0).tolist()
    candidates = [(w, k) for k, (w, im) in enumerate(zip(wr.tolist(), wi.tolist())) if im == 0.0 and c[k] > 1e-12]
    if not candidates:
        return None
    j = min(candidates)[1]
    v1 = V[:, j] / np.sqrt(c[j])
    return np.concatenate([v1, -(X @ v1)])  # v2 = -S22^-1 S12^T v1


def quadric_parameters(v: np.ndarray, p0: np.ndarray, scale: float):
    """(center (3,), radii (3,) descending, rotation (3, 3)) in mm and the frame of p0, of
    the quadric v given in coordinates (x - p0) / scale; None when it is not a real ellipsoid."""
    a, b, c, f, g, h, p, q, r, d = v.tolist()  # floats: unpacking NumPy scalars costs more
    A = np.array([[a, h, g], [h, b, f], [g, f, c]])
    _, _, x, info = lapack.dgesv(A, v[6:9])
    if info != 0:
        return None
    w = -x
    mu = w @ A @ w - d
    lam, R, info = lapack.dsyevd(A / mu, compute_v=1)
    if info != 0 or not (lam[0] > 0.0 and np.isfinite(lam[2])):
        return None
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R.tolist()
    det = r00 * (r11 * r22 - r12 * r21) - r01 * (r10 * r22 - r12 * r20) + r02 * (r10 * r21 - r11 * r20)
    if det < 0.0:  # eigenvectors come with arbitrary signs: make the frame right-handed
        R[:, 2] = -R[:, 2]
    return p0 + scale * w, scale / np.sqrt(lam), R


# dQ/dx = 2(a x + h y + g z + p), dQ/dy = 2(h x + b y + f z + q), dQ/dz = 2(g x + f y + c z + r):
# row i lists the coefficients of v multiplying [x, y, z, 1] in component i.
_GRAD_ROWS = np.array([[0, 5, 4, 6], [5, 1, 3, 7], [4, 3, 2, 8]])
_MOMENT_SCALE = np.multiply.outer([0.5, 0.5, 0.5, 1.0], [0.5, 0.5, 0.5, 1.0])  # S[6:, 6:] is in [2x, 2y, 2z, 1]


def taubin_residual(S: np.ndarray, v: np.ndarray):
    """RMS point-to-surface distance (scaled units) of quadric v (10,) -- or of each row
    of v (k, 10) -- over the points of S, in Taubin's first-order form
    sqrt(sum Q^2 / sum |grad Q|^2), from the moments alone: sum Q^2 = v^T S v and
    sum |grad Q|^2 = 4 sum_i w_i^T M w_i with w_i = v[rows_i] and M the second moments
    of [x, y, z, 1]. O(1) whatever the number of points."""
    V = v if v.ndim == 2 else v[None]
    W = V[:, _GRAD_ROWS]  # (k, 3, 4)
    g2 = 4.0 * ((W @ (S[6:, 6:] * _MOMENT_SCALE)) * W).sum(axis=(1, 2))
    q2 = ((V @ S) * V).sum(axis=1)
    r = [(max(q, 0.0) / g) ** 0.5 if g > 0.0 else float("inf") for q, g in zip(q2.tolist(), g2.tolist())]
    return np.array(r) if v.ndim == 2 else r[0]


def fit_scatter(S: np.ndarray, p0: np.ndarray, scale: float = LENGTH_SCALE_MM, check_spread: bool = True) -> EllipsoidFit:
    """Fit an ellipsoid to the points summarised by scatter matrix S (see module doc).
    `check_spread=False` skips the collinear/coplanar test (for a caller that knows the
    cloud is already spread in 3-D); too few points are always refused."""
    reason = degeneracy(S) if check_spread else ("too_few_points" if S[9, 9] < MIN_POINTS else None)
    if reason is not None:
        return EllipsoidFit(reason)
    try:
        v = solve_scatter(S)
    except np.linalg.LinAlgError:
        return EllipsoidFit("coplanar")
    params = None if v is None else quadric_parameters(v, p0, scale)
    if params is None:
        return EllipsoidFit("not_ellipsoid")
    return EllipsoidFit("ok", *params, v=v)


def fit_ellipsoid(P) -> Ellipsoid:
    """Ellipsoid-specific least-squares fit to points P (N >= 9, mm, any frame).

    Returns an Ellipsoid (centre, semi-axes, rotation) in the frame of P. Raises
    ValueError naming the reason when the points cannot define an ellipsoid (fewer
    than 9, collinear, coplanar, or a best quadric that is not an ellipsoid).
    """
    P = as_points(P, "P")
    p0 = P.mean(axis=0) if len(P) else np.zeros(3)
    Mrows = design_rows((P - p0) / LENGTH_SCALE_MM)
    fit = fit_scatter(Mrows.T @ Mrows, p0)
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

    def __init__(self):
        self.S = np.zeros((10, 10))
        self._n = 0  # points in S (its [9, 9] entry, kept as an int)
        self.p0: np.ndarray | None = None
        self.last_ok: EllipsoidFit | None = None
        self._spread_checked_at = 0  # point count at the last passed spread test (0: none)

    @property
    def n_points(self) -> int:
        return self._n

    def scaled(self, P: np.ndarray) -> np.ndarray:
        """Points (N, 3) mm in the fit's centred, scaled coordinates."""
        return (P - self.p0) / LENGTH_SCALE_MM

    def add(self, P: np.ndarray) -> None:
        """Accumulate finite points P (N, 3) mm (the caller filters non-finite ones)."""
        if len(P) == 0:
            return
        if self.p0 is None:
            self.p0 = np.array(P[0], dtype=float)
        if len(P) == 1:  # the per-A-scan path: one rank-1 update, no temporaries
            x, y, z = (P[0] - self.p0) / LENGTH_SCALE_MM
            m = np.array([x * x, y * y, z * z, 2 * y * z, 2 * x * z, 2 * x * y, 2 * x, 2 * y, 2 * z, 1.0])
            self.S += np.multiply.outer(m, m)
            self._n += 1
            return
        M = design_rows(self.scaled(P))
        self.S += M.T @ M
        self._n += len(P)

    def fit(self) -> EllipsoidFit:
        """Refit from all points so far; keeps `last_ok` on failure."""
        if self.p0 is None:
            return EllipsoidFit("too_few_points")
        # Adding points only widens a cloud's scatter about its mean, so once spread in
        # 3-D it stays so; the ratio test is still repeated every SPREAD_RECHECK points.
        n = self.n_points
        check = not self._spread_checked_at or n - self._spread_checked_at >= self.SPREAD_RECHECK
        result = fit_scatter(self.S, self.p0, check_spread=check)
        if check:
            self._spread_checked_at = n if result.status not in ("collinear", "coplanar", "too_few_points") else 0
        if result.ok:
            self.last_ok = result
        return result
