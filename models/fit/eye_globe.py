"""The eye globe: the ellipsoid whose semi-axes are an eye's that lies nearest the data,
for where the least-squares ellipsoid is none (the pointed eye's posterior paraboloid
fits a 129-177 x 27-31 x 27-31 mm one) and the robust globe is not taken.

Semi-axes within `EYE_RADII_MM` and the longest at most `EYE_AXIS_RATIO_MAX` times the
shortest (models.adaptive.model, where both are defined and why), fitted to the
least-squares ellipsoid's own scatter matrix S (models.fit.quadric_kernels: the design
rows of every point taken, in the scaled coordinates (p - p0) / scale), so a refit costs
no pass over the points: with S = L L^T the data's cost h^2 v^T S v / N is the squared
norm of the ten residuals h L^T v / sqrt(N) (v the quadric's coefficients, h half the
mean semi-axis: the algebraic residual of a point near the surface times h is its
distance from it, so the cost is about the mean squared distance of the points, mm^2).
Known points of the eye wall (`wall_W`: the trocars', whose cannulas pass through it)
weigh WALL_SHARE of the data together: one of them pins the globe where the scan does
not look, in front of the equator. Levenberg-Marquardt over the centre, the semi-axes (a smooth map onto
the eye's: _radii) and a rotation vector about the last rotation; forward-difference
Jacobian (13 x 10 at most: one refit is a few hundred evaluations of ~200 operations).

Measured on the loop's spiral (pointed eye, the local model on top, the default
sensor): the sphere under the local model leaves MAE 1,199 um over the paper's reference
region (1,838 um over its unscanned 65 %, seed 0); this globe with the trocar 420 um
(640), seeds 0-4 417-421 um; fitted to the data alone (a prototype) 886 um. The trocar's
weight hardly matters (a thirtieth, a tenth, a third of the data: 421, 419, 417 um): the
fit passes through it. Apex 2.5 / 3 / 4 / 6 mm: 461 / 512 / 626 / 894 um (the sphere at
4 mm: 1,533). Scanned p95 and 3-sigma coverage as with the sphere (24 um, 1.000): the
sd far from the data stays the sphere's.
Units: mm, rad.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models.fit.ellipsoid_fit import LENGTH_SCALE_MM
from models.fit.small_linalg import cholesky, pivoted_solve
from models.shapes.ellipsoid import Ellipsoid

WALL_SHARE = 0.1  # the wall points' weight, together, as a share of the data's (module docstring)
RATIO_PENALTY = 30.0  # residual per mm of the longest semi-axis beyond the ratio's bound
FIRST_ITERATIONS = 40  # Levenberg-Marquardt steps of a first fit; a refit is warm-started
REFIT_ITERATIONS = 4
# Every refit also starts afresh from spheres of these radii about the sphere fit's centre and keeps
# the lowest cost: warm-started alone, the pointed eye with a 4 mm apex stalled at 7.3 mm^2 (MAE
# 2,306 um); with these starts 0.19 mm^2 (626 um). One start costs ~15-30 us (make bench).
COLD_STARTS_MM = (10.0, 12.0)
_REGULARISATION = 1e-12  # relative to trace(S): S of a patch is near singular (a quadric's worth of data)


@njit(cache=True, inline="always")
def _rotation(R0, w, R):
    """R = R0 exp([w]x) (Rodrigues), written into R (3, 3); no temporaries."""
    t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    if t2 < 1e-24:
        a, b = 1.0, 0.5
    else:
        t = np.sqrt(t2)
        a, b = np.sin(t) / t, (1.0 - np.cos(t)) / t2
    # E = I + a K + b K^2 with K = [w]x; K^2 = w w^T - |w|^2 I
    e00 = 1.0 + b * (w[0] * w[0] - t2)
    e11 = 1.0 + b * (w[1] * w[1] - t2)
    e22 = 1.0 + b * (w[2] * w[2] - t2)
    e01, e10 = -a * w[2] + b * w[0] * w[1], a * w[2] + b * w[0] * w[1]
    e02, e20 = a * w[1] + b * w[0] * w[2], -a * w[1] + b * w[0] * w[2]
    e12, e21 = -a * w[0] + b * w[1] * w[2], a * w[0] + b * w[1] * w[2]
    for i in range(3):
        r0, r1, r2 = R0[i, 0], R0[i, 1], R0[i, 2]
        R[i, 0] = r0 * e00 + r1 * e10 + r2 * e20
        R[i, 1] = r0 * e01 + r1 * e11 + r2 * e21
        R[i, 2] = r0 * e02 + r1 * e12 + r2 * e22


@njit(cache=True)
def _residuals(x, R0, LT, n_eff, p0, scale, wall, wall_w, ratio_max, out, R, v):
    """The fit's residuals (module docstring) at x = [centre (3) mm, semi-axes (3) mm,
    rotation vector (3) about R0] into out (11 + len(wall),): the data's ten, the axis
    ratio's excess (RATIO_PENALTY per mm), the wall points'; returns the cost (their sum of
    squares, mm^2). R (3, 3), v (10,): work arrays."""
    _rotation(R0, x[6:9], R)
    r0, r1, r2 = x[3], x[4], x[5]
    h = (r0 + r1 + r2) / 6.0
    i0, i1, i2 = 1.0 / (r0 * r0), 1.0 / (r1 * r1), 1.0 / (r2 * r2)
    s2 = scale * scale
    a00 = s2 * (R[0, 0] * R[0, 0] * i0 + R[0, 1] * R[0, 1] * i1 + R[0, 2] * R[0, 2] * i2)
    a11 = s2 * (R[1, 0] * R[1, 0] * i0 + R[1, 1] * R[1, 1] * i1 + R[1, 2] * R[1, 2] * i2)
    a22 = s2 * (R[2, 0] * R[2, 0] * i0 + R[2, 1] * R[2, 1] * i1 + R[2, 2] * R[2, 2] * i2)
    a12 = s2 * (R[1, 0] * R[2, 0] * i0 + R[1, 1] * R[2, 1] * i1 + R[1, 2] * R[2, 2] * i2)
    a02 = s2 * (R[0, 0] * R[2, 0] * i0 + R[0, 1] * R[2, 1] * i1 + R[0, 2] * R[2, 2] * i2)
    a01 = s2 * (R[0, 0] * R[1, 0] * i0 + R[0, 1] * R[1, 1] * i1 + R[0, 2] * R[1, 2] * i2)
    c0, c1, c2 = (x[0] - p0[0]) / scale, (x[1] - p0[1]) / scale, (x[2] - p0[2]) / scale
    b0 = a00 * c0 + a01 * c1 + a02 * c2
    b1 = a01 * c0 + a11 * c1 + a12 * c2
    b2 = a02 * c0 + a12 * c1 + a22 * c2
    v[0], v[1], v[2], v[3], v[4], v[5] = a00, a11, a22, a12, a02, a01
    v[6], v[7], v[8] = -b0, -b1, -b2
    v[9] = c0 * b0 + c1 * b1 + c2 * b2 - 1.0
    g = h / np.sqrt(n_eff)
    cost = 0.0
    for i in range(10):
        acc = 0.0
        for j in range(i, 10):
            acc += LT[i, j] * v[j]
        out[i] = g * acc
        cost += out[i] * out[i]
    out[10] = RATIO_PENALTY * max(0.0, max(r0, r1, r2) - ratio_max * min(r0, r1, r2))
    cost += out[10] * out[10]
    for k in range(wall.shape[0]):
        d0, d1, d2 = wall[k, 0] - x[0], wall[k, 1] - x[1], wall[k, 2] - x[2]
        q0 = R[0, 0] * d0 + R[1, 0] * d1 + R[2, 0] * d2
        q1 = R[0, 1] * d0 + R[1, 1] * d1 + R[2, 1] * d2
        q2 = R[0, 2] * d0 + R[1, 2] * d1 + R[2, 2] * d2
        f = q0 * q0 * i0 + q1 * q1 * i1 + q2 * q2 * i2 - 1.0
        out[11 + k] = wall_w * h * f
        cost += out[11 + k] * out[11 + k]
    return cost


@njit(cache=True)
def fit_eye_globe(S, p0, scale, x, R0, wall, wall_share, r_lo, r_hi, ratio_max, iterations, damping):
    """(cost mm^2, damping) after up to `iterations` Levenberg-Marquardt steps from x =
    [centre (3) mm, semi-axes (3) mm] and rotation R0 (3, 3), both updated in place (the
    rotation vector folded into R0 after each step); the semi-axes clamped to
    [r_lo, r_hi] after each step, their ratio beyond ratio_max a penalty residual. `wall`
    (K, 3) mm: known points of the eye wall, weighing `wall_share` of the data together;
    `damping` the first step's. Cost NaN when S holds no points or cannot be factored
    (x, R0 untouched)."""
    n_eff = S[9, 9]
    m = 11 + wall.shape[0]
    if not (n_eff > 0.0):
        return np.nan, damping
    tr = 0.0
    for i in range(10):
        tr += S[i, i]
    Sr = S.copy()
    for i in range(10):
        Sr[i, i] += _REGULARISATION * tr
    L, ok = cholesky(Sr)
    if not ok:
        return np.nan, damping
    LT = np.ascontiguousarray(L.T)
    wall_w = np.sqrt(wall_share / wall.shape[0]) if wall.shape[0] else 0.0
    y = np.zeros(9)
    y[0:6] = x[0:6]
    for i in range(3, 6):
        y[i] = min(max(y[i], r_lo), r_hi)
    res, trial_res = np.empty(m), np.empty(m)
    Rw, vw = np.empty((3, 3)), np.empty(10)
    cost = _residuals(y, R0, LT, n_eff, p0, scale, wall, wall_w, ratio_max, res, Rw, vw)
    J = np.empty((m, 9))
    yt = np.empty(9)
    R = np.empty((3, 3))
    for _ in range(iterations):
        for j in range(9):
            step = 1e-6 if j < 6 else 1e-7
            yt[:] = y
            yt[j] += step
            _residuals(yt, R0, LT, n_eff, p0, scale, wall, wall_w, ratio_max, trial_res, Rw, vw)
            for i in range(m):
                J[i, j] = (trial_res[i] - res[i]) / step
        JTJ = J.T @ J
        g = J.T @ res
        improved = False
        for _try in range(8):
            M = JTJ.copy()
            for i in range(9):
                M[i, i] += damping * (JTJ[i, i] + 1e-12)
            d = pivoted_solve(M, -g, 1e-300)
            yt[:] = y + d
            for i in range(3, 6):
                yt[i] = min(max(yt[i], r_lo), r_hi)
            trial = _residuals(yt, R0, LT, n_eff, p0, scale, wall, wall_w, ratio_max, trial_res, Rw, vw)
            if trial < cost:
                _rotation(R0, yt[6:9], R)
                R0[:, :] = R
                yt[6:9] = 0.0
                y[:] = yt
                cost = _residuals(y, R0, LT, n_eff, p0, scale, wall, wall_w, ratio_max, res, Rw, vw)
                damping = max(damping / 3.0, 1e-9)
                improved = True
                break
            damping *= 4.0
        if not improved:
            break
    x[0:6] = y[0:6]
    return cost, damping


class EyeGlobe:
    """The eye globe of a model's least-squares scatter matrix (module docstring), refitted
    from the last fit every `every` points; `ellipsoid` the last good fit (None before one).

    `wall_W`: None or (K, 3) mm, known points of the eye wall in the frame of the points
    (the trocars'). `r_range` and `ratio_max`: the eye's semi-axes and axis ratio
    (models.adaptive.model.EYE_RADII_MM, EYE_AXIS_RATIO_MAX)."""

    def __init__(self, r_range: tuple[float, float], ratio_max: float, wall_W=None, every: int = 20):
        wall = np.zeros((0, 3)) if wall_W is None else np.asarray(wall_W, dtype=float).reshape(-1, 3)
        if not np.all(np.isfinite(wall)):
            raise ValueError(f"wall_W must hold finite points (K, 3) mm, got {wall_W!r}")
        self.wall = np.ascontiguousarray(wall)
        self.r_range, self.ratio_max, self.every = (float(r_range[0]), float(r_range[1])), float(ratio_max), int(every)
        self.ellipsoid = None
        self.cost_mm2 = np.nan
        self._x = None
        self._R = np.eye(3)
        self._at = -1

    def due(self, n_points: int) -> bool:
        """Whether a model of n_points refits it (every `every` points)."""
        return self._x is None or n_points - self._at >= self.every

    def refit(self, S, p0, n_points: int, center, radius: float, rotation) -> None:
        """Refit to the scatter matrix S (10, 10) about p0 (scale LENGTH_SCALE_MM); the first
        fit starts from a sphere of `radius` (mm, clipped to the eye's) about `center` with
        its axes along `rotation` (3, 3). A failed fit keeps the last good one."""
        first = self._x is None
        if first:
            r = float(np.clip(radius, *self.r_range))
            self._x = np.concatenate([np.asarray(center, dtype=float), [r, r, r]])
            self._R = np.array(rotation, dtype=float)
        x, R = self._x.copy(), self._R.copy()
        cost, _ = fit_eye_globe(S, p0, LENGTH_SCALE_MM, x, R, self.wall, WALL_SHARE, *self.r_range, self.ratio_max,
                                      FIRST_ITERATIONS if first else REFIT_ITERATIONS, 1e-3)
        for r0 in COLD_STARTS_MM:  # an LM started from the last fit can stall in a poor minimum
            xc, Rc = np.concatenate([np.asarray(center, dtype=float), [r0, r0, r0]]), np.array(rotation, dtype=float)
            cc, _ = fit_eye_globe(S, p0, LENGTH_SCALE_MM, xc, Rc, self.wall, WALL_SHARE, *self.r_range, self.ratio_max,
                                   FIRST_ITERATIONS, 1e-3)
            if cc < cost or not np.isfinite(cost):
                x, R, cost = xc, Rc, cc
        self._at = n_points
        if not (np.isfinite(cost) and np.all(np.isfinite(x)) and np.all(np.isfinite(R))):
            if first:
                self._x = None
            return
        x[3:6] = np.minimum(x[3:6], self.ratio_max * x[3:6].min())  # the penalty's slack (~1e-4 mm) taken off
        U, _, Vt = np.linalg.svd(R)  # the nearest rotation: the folded steps' rounding drifts
        self._x, self._R, self.cost_mm2 = x, U @ Vt, float(cost)
        self.ellipsoid = Ellipsoid(x[:3], x[3:6], self._R)
