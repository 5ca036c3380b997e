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
not look, in front of the equator. Levenberg-Marquardt over the centre, the semi-axes (clamped to
EYE_RADII_MM after each step, their ratio beyond the bound a penalty residual) and a
rotation vector about the last rotation; forward-difference Jacobian (11 + K rows, 9
columns: a step is about 20 evaluations of ~200 operations). An LM step from the last fit
can stall in a poor minimum: three candidates from different spheres are kept (EyeGlobe).

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
from models.shapes.validation import as_points

WALL_SHARE = 0.1  # the wall points' weight, together, as a share of the data's (module docstring)
RATIO_PENALTY = 30.0  # residual per mm of the longest semi-axis beyond the ratio's bound
REFIT_ITERATIONS = 12  # Levenberg-Marquardt steps per refit, of one of the candidates in turn
# The candidates: fits started from spheres of these radii about the sphere fit's centre,
# advanced in turn, the lowest cost published. One LM alone stalled on the pointed eye with
# a 4 mm apex at 7.3 mm^2 (MAE 2,306 um); the best of three reached 0.195 mm^2 (667 um). A
# refit: median 39-60 us, max 149 us (make bench); with 4 steps, 496 / 958 um on the default
# and the 4 mm apex (12 steps: 430 / 667; the three run to convergence at every refit:
# 419 / 626, but ~340 us each).
START_RADII_MM = (None, 10.0, 12.0)  # None: the sphere fit's own radius
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
def factor_scatter(S):
    """(L^T (10, 10), N, ok): the transposed Cholesky factor of S (regularised, module
    docstring) and its number of points; not ok when S holds none or cannot be factored."""
    n_eff = S[9, 9]
    if not (n_eff > 0.0):
        return np.zeros((10, 10)), n_eff, False
    tr = 0.0
    for i in range(10):
        tr += S[i, i]
    Sr = S.copy()
    for i in range(10):
        Sr[i, i] += _REGULARISATION * tr
    L, ok = cholesky(Sr)
    return np.ascontiguousarray(L.T), n_eff, ok


@njit(cache=True)
def fit_eye_globe(LT, n_eff, p0, scale, x, R0, wall, wall_share, r_lo, r_hi, ratio_max, iterations):
    """The cost (mm^2) after up to `iterations` Levenberg-Marquardt steps (0: the cost of
    x itself) on the factored scatter matrix (factor_scatter: LT, n_eff) from x = [centre
    (3) mm, semi-axes (3) mm] and rotation R0 (3, 3), both updated in place (the rotation
    vector folded into R0 after each step); the semi-axes clamped to [r_lo, r_hi] after
    each step, their ratio beyond ratio_max a penalty residual. `wall` (K, 3) mm: known
    points of the eye wall, weighing `wall_share` of the data together."""
    m = 11 + wall.shape[0]
    wall_w = np.sqrt(wall_share / wall.shape[0]) if wall.shape[0] else 0.0
    damping = 1e-3
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
    hi = ratio_max * min(x[3], x[4], x[5])  # the penalty's slack (~1e-4 mm) taken off
    for i in range(3, 6):
        x[i] = min(x[i], hi)
    _orthonormalise(R0)  # the folded steps' rounding drifts
    return cost


@njit(cache=True, inline="always")
def _orthonormalise(R):
    """R (3, 3) made a rotation again, in place (Gram-Schmidt on its columns, the third
    their cross product)."""
    n = np.sqrt(R[0, 0] ** 2 + R[1, 0] ** 2 + R[2, 0] ** 2)
    for i in range(3):
        R[i, 0] /= n
    d = R[0, 0] * R[0, 1] + R[1, 0] * R[1, 1] + R[2, 0] * R[2, 1]
    for i in range(3):
        R[i, 1] -= d * R[i, 0]
    n = np.sqrt(R[0, 1] ** 2 + R[1, 1] ** 2 + R[2, 1] ** 2)
    for i in range(3):
        R[i, 1] /= n
    R[0, 2] = R[1, 0] * R[2, 1] - R[2, 0] * R[1, 1]
    R[1, 2] = R[2, 0] * R[0, 1] - R[0, 0] * R[2, 1]
    R[2, 2] = R[0, 0] * R[1, 1] - R[1, 0] * R[0, 1]


@njit(cache=True)
def refit_candidates(S, p0, scale, X, Rs, started, k, iterations, sphere, wall, wall_share, r_lo, r_hi, ratio_max):
    """One refit (EyeGlobe.refit): candidate k of X (c, 6) [centre, semi-axes] mm and
    Rs (c, 3, 3) advanced by `iterations` steps in place, then every started candidate's
    cost and the sphere's (`sphere` [centre, radius] mm, clipped to [r_lo, r_hi]) on S.
    Returns (index of the lowest-cost candidate or -1 when none is below the sphere or
    S cannot be factored, its cost mm^2); a failed candidate is marked not started. S is
    factored once (factor_scatter) for the steps and every cost."""
    LT, n_eff, ok = factor_scatter(S)
    if not ok:  # no candidate's cost is defined: k starts again at its next turn
        started[k] = False
        return -1, np.nan
    x, R = X[k].copy(), Rs[k].copy()
    cost = fit_eye_globe(LT, n_eff, p0, scale, x, R, wall, wall_share, r_lo, r_hi, ratio_max, iterations)
    ok = np.isfinite(cost)
    for i in range(6):
        ok = ok and np.isfinite(x[i])
    if ok:
        X[k], Rs[k] = x, R
    else:
        started[k] = False
    r = min(max(sphere[3], r_lo), r_hi)
    xs = np.array([sphere[0], sphere[1], sphere[2], r, r, r])
    best, best_cost = -1, fit_eye_globe(LT, n_eff, p0, scale, xs, np.eye(3), wall, wall_share, r_lo, r_hi, ratio_max, 0)
    for j in range(X.shape[0]):
        if started[j]:
            cj = cost if j == k else fit_eye_globe(LT, n_eff, p0, scale, X[j].copy(), Rs[j].copy(), wall, wall_share,
                                                   r_lo, r_hi, ratio_max, 0)
            if cj < best_cost:
                best, best_cost = j, cj
    return best, best_cost


class EyeGlobe:
    """The eye globe of a model's least-squares scatter matrix (module docstring), refitted
    every `every` points; `ellipsoid` the best fit while it fits the data and the wall
    points better than the sphere fit does (else None: the sphere stands), `cost_mm2` its cost.

    Three candidates (START_RADII_MM) are kept; each refit advances one of them in turn by
    REFIT_ITERATIONS steps (a few tens of us: make bench) and publishes the lowest cost
    on the current scatter matrix. `wall_W`: None or (K, 3) mm, known points of the eye
    wall in the frame of the points (the trocars'). `r_range` and `ratio_max`: the eye's
    semi-axes and axis ratio (models.adaptive.model.EYE_RADII_MM, EYE_AXIS_RATIO_MAX)."""

    def __init__(self, r_range: tuple[float, float], ratio_max: float, wall_W=None, every: int = 20):
        self.wall = np.zeros((0, 3)) if wall_W is None else np.ascontiguousarray(as_points(wall_W, "wall_W"))
        self.r_range, self.ratio_max, self.every = (float(r_range[0]), float(r_range[1])), float(ratio_max), int(every)
        self.ellipsoid = None
        self.cost_mm2 = np.nan
        n = len(START_RADII_MM)
        self._X, self._Rs, self._started = np.zeros((n, 6)), np.zeros((n, 3, 3)), np.zeros(n, dtype=np.bool_)
        self._sphere = np.zeros(4)
        self._turn = 0
        self._at = -1

    def due(self, n_points: int) -> bool:
        """Whether a model of n_points refits it (every `every` points)."""
        return self._at < 0 or n_points - self._at >= self.every

    def refit(self, S, p0, n_points: int, center, radius: float, rotation) -> None:
        """Advance one candidate on the scatter matrix S (10, 10) about p0 (scale
        LENGTH_SCALE_MM) and publish the best (refit_candidates: one compiled call); a
        candidate starts from a sphere about `center` (mm) of its START_RADII_MM radius
        (None: the sphere fit's `radius`, mm), clipped to the eye's, with its axes along
        `rotation` (3, 3). A candidate whose fit fails starts again at its next turn."""
        self._at = n_points
        k = self._turn
        self._turn = (k + 1) % len(START_RADII_MM)
        sphere = self._sphere
        sphere[:3], sphere[3] = center, radius
        if not self._started[k]:
            r0 = min(max(radius if START_RADII_MM[k] is None else START_RADII_MM[k], self.r_range[0]), self.r_range[1])
            self._X[k, :3], self._X[k, 3:] = center, r0
            self._Rs[k] = rotation
            self._started[k] = True
        best, cost = refit_candidates(S, p0, LENGTH_SCALE_MM, self._X, self._Rs, self._started, k, REFIT_ITERATIONS,
                                      sphere, self.wall, WALL_SHARE, *self.r_range, self.ratio_max)
        if best < 0:
            self.ellipsoid, self.cost_mm2 = None, np.nan
        elif self.ellipsoid is None or cost != self.cost_mm2:
            self.ellipsoid, self.cost_mm2 = Ellipsoid(self._X[best, :3], self._X[best, 3:], self._Rs[best]), float(cost)

    def cost_of(self, S, p0, center, radii, rotation) -> float:
        """The fit's cost (mm^2: the data's mean squared distance and the wall points'
        share, module docstring) of the ellipsoid (centre mm, semi-axes mm, rotation) on the
        scatter matrix S about p0; NaN when S holds no points or cannot be factored."""
        LT, n_eff, ok = factor_scatter(S)
        if not ok:
            return float("nan")
        x = np.concatenate([np.asarray(center, dtype=float), np.asarray(radii, dtype=float)])
        return float(fit_eye_globe(LT, n_eff, p0, LENGTH_SCALE_MM, x, np.array(rotation, dtype=float), self.wall,
                                   WALL_SHARE, *self.r_range, self.ratio_max, 0))
