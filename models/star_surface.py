"""Closed surfaces given by a radial function r = rho(u) about their centre (star-shaped).

The composite eye shapes (pointed, staphyloma, detached) are such surfaces in the eye
frame E. This module answers the geometric questions for the radial functions of
`RADIAL_KINDS` (compiled with numba: the sensor casts rays on the true retina at 2 kHz):
first ray hits (a march whose steps are bounded by the radial function's slope, then
regula falsi, sub-nanometre), exact signed distance (seeded from the local minima of the
distance over a dense surface cloud, then Levenberg-Marquardt on the surface
parametrisation), normals and surface samples.

The radial functions are one compiled family (numba caches a kernel per function, not
per closure, so the kinds share one set of kernels) with their parameters in a flat
array; `models.eyes` builds the eye shapes from them.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from models._validation import as_points, as_positive, as_vector3
from models.rays import incidence_rad, rays_in_frame
from models.sampling import unit_sphere_grid

RADIAL_KINDS = ("ellipsoid", "pointed", "staphyloma", "detached")
_ELLIPSOID, _POINTED, _STAPHYLOMA, _DETACHED = range(len(RADIAL_KINDS))
CLIP_MM = 1e-5  # a ray's excursion across the surface shallower than this may go unseen (10 nm)
COARSE_STEP = 8  # the closest-point search scans every 8th row and column of the cloud first
MAX_COARSE_MINIMA = 8  # coarse local minima refined per query, the nearest first
SEED_TIE_MM = 0.05  # cloud minima this close to the best are all refined (_seeds)
SLOPE_SAFETY = 2.0  # the sampled slope of rho times this bounds the true one (StarSurface.march_constants)
MARCH_STEP_MM = 0.05  # the ray march's shortest step (StarSurface.ray_cast)


@njit(cache=True)
def _rho(kind, p, x, y, z):
    """rho (mm) in the unit direction (x, y, z) for the radial function `kind` with
    parameters p (layout: the builders below): p[0:3] = 1 / semi-axes^2 of the base
    ellipsoid (mm^-2), then the kind's own parameters."""
    ell = 1.0 / np.sqrt(x * x * p[0] + y * y * p[1] + z * z * p[2])
    if kind == _ELLIPSOID or (kind == _POINTED and z >= 0.0):
        return ell
    if kind == _POINTED:  # root of h k r^2 - z r - h = 0, cancellation-free for z < 0
        h = p[3]
        return 2.0 * h / (-z + np.sqrt(z * z + 4.0 * h * h * (x * x * p[0] + y * y * p[1])))
    cos = x * p[3] + y * p[4] + z * p[5]
    if kind == _STAPHYLOMA:  # C1 smooth maximum of the ellipsoid and the sphere
        dist, radius, blend = p[6], p[7], p[8]
        r_sph = dist * cos + np.sqrt(radius * radius - dist * dist * (1.0 - cos * cos))
        w = max(blend - abs(ell - r_sph), 0.0) / blend
        return max(ell, r_sph) + 0.25 * blend * w * w
    t = np.arccos(min(max(cos, -1.0), 1.0)) / p[6]  # _DETACHED: the bump's angle ratio
    return ell - p[7] * (1.0 - t * t) ** 2 if t < 1.0 else ell


@njit(cache=True)
def _rho_batch(kind, p, U):
    out = np.empty(U.shape[0])
    for m in range(U.shape[0]):
        out[m] = _rho(kind, p, U[m, 0], U[m, 1], U[m, 2])
    return out


class RadialFunction(NamedTuple):
    """A radial function rho(u) (mm) of the kind RADIAL_KINDS[kind] with parameters
    `params` (see `_rho`); call it on (M, 3) unit directions for (M,) radii in mm."""

    kind: int
    params: np.ndarray

    def __call__(self, U: np.ndarray) -> np.ndarray:
        return _rho_batch(self.kind, self.params, np.ascontiguousarray(U, dtype=float))


def _with_base(radii, *extra) -> np.ndarray:
    """The parameters of `_rho`: 1 / radii^2 (radii (3,) mm, each > 0), then `extra`."""
    radii = np.array([as_positive(r, "semi-axis (mm)") for r in np.ravel(radii)])
    if radii.shape != (3,):
        raise ValueError(f"radii must be 3 semi-axes (mm), got {radii.shape[0]}")
    return np.concatenate([1.0 / radii**2, np.asarray(extra, dtype=float)])


def _unit(centre_dir) -> np.ndarray:
    u = as_vector3(centre_dir, "centre_dir")
    if not abs(np.linalg.norm(u) - 1.0) <= 1e-9:
        raise ValueError(f"centre_dir must be a unit vector, got norm {np.linalg.norm(u)}")
    return u


def ellipsoid_radial(radii) -> RadialFunction:
    """The ellipsoid with semi-axes `radii` (3,) mm along the frame's axes."""
    return RadialFunction(_ELLIPSOID, _with_base(radii))


def paraboloid_backed_radial(radii, depth_mm: float) -> RadialFunction:
    """The ellipsoid for z >= 0; for z < 0 the paraboloid z = -h + h (x^2/a^2 + y^2/b^2),
    h = `depth_mm`, through the ellipsoid's equator (a, b: its first two semi-axes, mm)."""
    return RadialFunction(_POINTED, _with_base(radii, as_positive(depth_mm, "depth_mm")))


def sphere_union_radial(radii, centre_dir, centre_dist_mm: float, radius_mm: float, blend_mm: float) -> RadialFunction:
    """The ellipsoid and the sphere of radius `radius_mm` centred `centre_dist_mm` along the
    unit `centre_dir` (3,), joined by a C1 smooth maximum of radial width `blend_mm`
    (0 < centre_dist_mm < radius_mm: the sphere holds the centre, so it is star-shaped)."""
    radius_mm = as_positive(radius_mm, "radius_mm")
    if not 0.0 < centre_dist_mm < radius_mm:
        raise ValueError(f"centre_dist_mm must lie in (0, {radius_mm}) mm, got {centre_dist_mm}")
    return RadialFunction(_STAPHYLOMA, _with_base(radii, *_unit(centre_dir), centre_dist_mm, radius_mm,
                                                  as_positive(blend_mm, "blend_mm")))


def bump_radial(radii, centre_dir, half_angle_rad: float, height_mm: float) -> RadialFunction:
    """The ellipsoid lowered by height_mm (1 - t^2)^2 within `half_angle_rad` of the unit
    `centre_dir` (3,), t the angle from it over the half-angle (0 < half_angle_rad <= pi,
    0 <= height_mm below the ellipsoid's smallest semi-axis: rho stays > 0)."""
    base = _with_base(radii, *_unit(centre_dir), as_positive(half_angle_rad, "half_angle_rad"), height_mm)
    if half_angle_rad > np.pi:
        raise ValueError(f"half_angle_rad must lie in (0, pi], got {half_angle_rad}")
    if not 0.0 <= height_mm < 1.0 / np.sqrt(base[:3].max()):
        raise ValueError(f"height_mm must lie in [0, {1.0 / np.sqrt(base[:3].max()):.3f}) mm, got {height_mm}")
    return RadialFunction(_DETACHED, base)


@njit(cache=True)
def _inside_value(kind, p, x, y, z):
    """|x| - rho(x/|x|) (mm) at the point (x, y, z) mm; the origin counts as direction -z."""
    r = np.sqrt(x * x + y * y + z * z)
    if r > 0.0:
        return r - _rho(kind, p, x / r, y / r, z / r)
    return -_rho(kind, p, 0.0, 0.0, -1.0)


@njit(cache=True)
def _inside_values(kind, p, X):
    out = np.empty(X.shape[0])
    for m in range(X.shape[0]):
        out[m] = _inside_value(kind, p, X[m, 0], X[m, 1], X[m, 2])
    return out


@njit(cache=True)
def _on_ray(kind, p, o, d, t):
    """The inside value (mm) at o + t d (o, d: (3,) mm and unit)."""
    return _inside_value(kind, p, o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2])


@njit(cache=True)
def _refine(kind, p, o, d, lo, hi, f_lo, f_hi, s0):
    """The crossing in [lo, hi] (mm along the ray; f_lo on the starting side s0, f_hi not)
    to ~1e-13 mm: regula falsi with the Illinois modification (superlinear: ~10
    evaluations instead of 60 halvings), halving where the secant leaves the bracket."""
    side = 0.0  # +1 / -1: which end moved last (Illinois halves the other's value)
    for _ in range(80):
        width = hi - lo
        if width <= 1e-13 * max(hi, 1.0):
            break
        den = f_hi - f_lo
        t = lo - f_lo * width / den if den != 0.0 else 0.5 * (lo + hi)
        if not (lo < t < hi):
            t = 0.5 * (lo + hi)
        f = _on_ray(kind, p, o, d, t)
        if np.sign(f) == s0:  # still on the starting side: t becomes the new lo
            if side == 1.0:
                f_hi *= 0.5
            lo, f_lo, side = t, f, 1.0
        else:
            if side == -1.0:
                f_lo *= 0.5
            hi, f_hi, side = t, f, -1.0
    return 0.5 * (lo + hi)


@njit(cache=True)
def _clip_search(kind, p, o, d, s0, lip, a, f_a, b, f_b):
    """(found, lo, f_lo, hi, f_hi): the first sign change in [a, b], whose ends are both on
    the side s0, by bisection, left half first. With |df/dt| <= lip, a part [l, r] with end
    values f_l, f_r holds no excursion deeper than CLIP_MM when lip (r - l) - |f_l| - |f_r|
    <= 2 CLIP_MM, and is not split further."""
    # depth first: the stack holds at most one part per level, and a part narrower than
    # 2 CLIP_MM / lip is never split (< 40 levels below a step of up to 2 r_out)
    stack = np.empty((64, 4))
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3] = a, f_a, b, f_b
    n = 1
    while n > 0:
        n -= 1
        l, f_l, r, f_r = stack[n, 0], stack[n, 1], stack[n, 2], stack[n, 3]
        if lip * (r - l) - abs(f_l) - abs(f_r) <= 2.0 * CLIP_MM:
            continue
        m = 0.5 * (l + r)
        f_m = _on_ray(kind, p, o, d, m)
        if np.sign(f_m) != s0:
            return True, l, f_l, m, f_m
        stack[n, 0], stack[n, 1], stack[n, 2], stack[n, 3] = m, f_m, r, f_r  # the right half waits
        stack[n + 1, 0], stack[n + 1, 1], stack[n + 1, 2], stack[n + 1, 3] = l, f_l, m, f_m
        n += 2
    return False, a, f_a, b, f_b


@njit(cache=True)
def _march(kind, p, o, d, s0, a, b, lip, step):
    """The first crossing (mm along the ray) in [a, b], NaN if none. From a sample with
    inside value f no crossing lies closer than |f| / lip, so the step is
    max(|f| / lip, step); a step whose end values leave room for an excursion deeper
    than CLIP_MM is searched by bisection."""
    t, f_t = a, _on_ray(kind, p, o, d, a)
    while t < b:
        t_next = min(t + max(abs(f_t) / lip, step), b)
        f_next = _on_ray(kind, p, o, d, t_next)
        if np.sign(f_next) != s0:
            return _refine(kind, p, o, d, t, t_next, f_t, f_next, s0)
        if s0 != 0.0:
            found, lo, f_lo, hi, f_hi = _clip_search(kind, p, o, d, s0, lip, t, f_t, t_next, f_next)
            if found:
                return _refine(kind, p, o, d, lo, hi, f_lo, f_hi, s0)
        t, f_t = t_next, f_next
    return np.nan


@njit(cache=True)
def _ray_hits(kind, p, O, D, r_in, r_out, lip, step, t_max):
    """(M,) first crossings (mm) along the unit rays D (M, 3) from O (M, 3) mm, NaN where
    none lies within t_max. The surface lies in the shell r_in <= |x| <= r_out, so each
    ray is marched only where it runs in that shell (up to two parts, closed form)."""
    out = np.full(O.shape[0], np.nan)
    for m in range(O.shape[0]):
        o, d = O[m], D[m]
        s0 = np.sign(_on_ray(kind, p, o, d, 0.0))
        b = o[0] * d[0] + o[1] * d[1] + o[2] * d[2]
        oo = o[0] * o[0] + o[1] * o[1] + o[2] * o[2]
        disc_out = b * b - oo + r_out * r_out
        if disc_out <= 0.0:
            continue  # the line misses the shell's outer sphere
        end = min(-b + np.sqrt(disc_out), t_max)
        disc_in = b * b - oo + r_in * r_in
        enter_in, leave_in = np.inf, np.inf  # the part inside the ball of radius r_in
        if disc_in > 0.0:
            enter_in, leave_in = -b - np.sqrt(disc_in), -b + np.sqrt(disc_in)
        parts = ((max(-b - np.sqrt(disc_out), 0.0), min(enter_in, end)), (max(leave_in, 0.0), end))
        for lo, hi in parts:
            if lo < hi:
                out[m] = _march(kind, p, o, d, s0, lo, hi, lip, step)
                if not np.isnan(out[m]):
                    break
    return out


@njit(cache=True)
def _tangent_basis(ux, uy, uz):
    """Two unit vectors (tuples) orthogonal to the unit (ux, uy, uz) and to each other."""
    hx, hy = (1.0, 0.0) if abs(ux) < 0.9 else (0.0, 1.0)  # helper (hx, hy, 0)
    e1x, e1y, e1z = -uz * hy, uz * hx, ux * hy - uy * hx  # u x helper
    n = np.sqrt(e1x * e1x + e1y * e1y + e1z * e1z)
    e1x, e1y, e1z = e1x / n, e1y / n, e1z / n
    return (e1x, e1y, e1z), (uy * e1z - uz * e1y, uz * e1x - ux * e1z, ux * e1y - uy * e1x)


@njit(cache=True)
def _surface_at(kind, p, u, e1, e2, a, b):
    """The surface point (tuple, mm) in the direction normalise(u + a e1 + b e2)."""
    x, y, z = u[0] + a * e1[0] + b * e2[0], u[1] + a * e1[1] + b * e2[1], u[2] + a * e1[2] + b * e2[2]
    n = np.sqrt(x * x + y * y + z * z)
    x, y, z = x / n, y / n, z / n
    r = _rho(kind, p, x, y, z)
    return r * x, r * y, r * z


@njit(cache=True)
def _closest_point(kind, p, q, u0, iterations):
    """The closest surface point (tuple, mm) to q (3,) mm from the seed direction u0
    (tuple): Levenberg-Marquardt on (a, b) -> surface point in normalise(u0 + a e1 + b e2),
    finite-difference Jacobian, steps accepted only if they reduce the distance."""
    e1, e2 = _tangent_basis(u0[0], u0[1], u0[2])
    a, b, lam, h = 0.0, 0.0, 1e-3, 1e-7
    X = _surface_at(kind, p, u0, e1, e2, a, b)
    cost = (X[0] - q[0]) ** 2 + (X[1] - q[1]) ** 2 + (X[2] - q[2]) ** 2
    for _ in range(iterations):
        Xa = _surface_at(kind, p, u0, e1, e2, a + h, b)
        Xb = _surface_at(kind, p, u0, e1, e2, a, b + h)
        jaa, jab, jbb, ga, gb = 0.0, 0.0, 0.0, 0.0, 0.0
        for k in range(3):
            ja, jb, r = (Xa[k] - X[k]) / h, (Xb[k] - X[k]) / h, X[k] - q[k]
            jaa, jab, jbb, ga, gb = jaa + ja * ja, jab + ja * jb, jbb + jb * jb, ga + ja * r, gb + jb * r
        damp = lam * (jaa + jbb)  # lam (trace I + 1e-12), as a fraction of the curvature
        A00, A01, A11 = jaa + damp + lam * 1e-12, jab + lam * 1e-12, jbb + damp + lam * 1e-12
        det = A00 * A11 - A01 * A01
        step_a, step_b = -(A11 * ga - A01 * gb) / det, -(A00 * gb - A01 * ga) / det
        X_trial = _surface_at(kind, p, u0, e1, e2, a + step_a, b + step_b)
        cost_trial = (X_trial[0] - q[0]) ** 2 + (X_trial[1] - q[1]) ** 2 + (X_trial[2] - q[2]) ** 2
        if cost_trial < cost:
            a, b, X, cost, lam = a + step_a, b + step_b, X_trial, cost_trial, lam * 0.3
        else:
            lam *= 10.0
        if max(abs(step_a), abs(step_b)) < 1e-12:
            break
    return X, cost


@njit(cache=True)
def _normal_inward(kind, p, u):
    """The unit inward normal (3,) at the surface point in the unit direction u (tuple)
    (finite differences of the parametrisation, 1e-6 rad)."""
    e1, e2 = _tangent_basis(u[0], u[1], u[2])
    X = np.array(_surface_at(kind, p, u, e1, e2, 0.0, 0.0))
    n = np.cross(np.array(_surface_at(kind, p, u, e1, e2, 1e-6, 0.0)) - X,
                 np.array(_surface_at(kind, p, u, e1, e2, 0.0, 1e-6)) - X)
    n /= np.linalg.norm(n)
    return -n if n @ X > 0.0 else n


@njit(cache=True)
def star_hits(kind, p, O_W, U_W, p_WE, R_WE, r_in, r_out, lip, step):
    """((M,) distance mm along the unit rays (O_W, U_W) (M, 3) in W to the surface of the
    radial function (kind, p) placed at (R_WE (3, 3), p_WE (3,) mm), NaN without a hit or
    with one only at or behind the origin; (M,) incidence rad between the ray and the
    surface's normal at the hit, NaN without a hit): `_ray_hits` (march constants r_in,
    r_out, lip of StarSurface.march_constants, step mm as in StarSurface.ray_cast) and
    `_normal_inward` at the hit's direction from the centre, in one compiled pass (the
    composite eyes' kernel of models.eyes.retina_hits). ValueError as
    models.rays.rays_in_frame."""
    O, D = rays_in_frame(O_W, U_W, p_WE, R_WE)
    d = _ray_hits(kind, p, O, D, r_in, r_out, lip, step, np.inf)
    incidence = np.full(O.shape[0], np.nan)
    for m in range(O.shape[0]):
        if not d[m] > 0.0:
            d[m] = np.nan
            continue
        x, y, z = O[m, 0] + d[m] * D[m, 0], O[m, 1] + d[m] * D[m, 1], O[m, 2] + d[m] * D[m, 2]
        r = np.sqrt(x * x + y * y + z * z)  # > r_in > 0: the surface lies in the shell
        n = _normal_inward(kind, p, (x / r, y / r, z / r))
        incidence[m] = incidence_rad(n[0] * D[m, 0] + n[1] * D[m, 1] + n[2] * D[m, 2], 1.0)
    return d, incidence


@njit(cache=True)
def _normals_batch(kind, p, U):
    N = np.empty_like(U)
    for m in range(U.shape[0]):
        N[m] = _normal_inward(kind, p, (U[m, 0], U[m, 1], U[m, 2]))
    return N


@njit(cache=True)
def _dist2(P, i, j, q):
    return (P[i, j, 0] - q[0]) ** 2 + (P[i, j, 1] - q[1]) ** 2 + (P[i, j, 2] - q[2]) ** 2


@njit(cache=True)
def _descend(P, q, i, j, stride, visited, stamp):
    """(i, j, squared distance mm^2): steepest descent of the distance to q over the cloud
    grid P (n_theta, n_phi, 3) from the sample (i, j), over the 8 neighbours `stride`
    samples away, then stride // 2, ..., 1 (periodic in phi); (-1, -1, inf) where the
    last stage joins the path of an earlier descent for the same q (marked `stamp` in
    `visited`, (n_theta, n_phi)), which ends at the same minimum."""
    best = _dist2(P, i, j, q)
    while stride >= 1:
        while True:
            if stride == 1:
                if visited[i, j] == stamp:
                    return -1, -1, np.inf
                visited[i, j] = stamp
            bi, bj = i, j
            for ii in range(i - stride, i + stride + 1, stride):
                if ii < 0 or ii >= P.shape[0]:
                    continue
                for jj in range(j - stride, j + stride + 1, stride):
                    d2 = _dist2(P, ii, jj % P.shape[1], q)
                    if d2 < best:
                        best, bi, bj = d2, ii, jj % P.shape[1]
            if bi == i and bj == j:
                break
            i, j = bi, bj
        stride //= 2
    return i, j, best


@njit(cache=True)
def _seeds(P, coarse, eta_rows, z_rows, q, k, eta_fine, D, minima, seeds, visited, stamp):
    """Fill `seeds` (S, 2) with cloud indices from which to search the closest point to q;
    return how many. `coarse` (n_i, n_j, 3) mm: the samples (k a + k // 2, k b + k // 2)
    of the cloud grid P, each standing for the k x k block of cloud samples around it,
    all within eta_rows[a] (mm) of it and within z_rows[a] = (z_min, z_max) (mm), so that
    rows whose z range lies farther from q than the nearest coarse sample so far are not
    scanned; D (n_i, n_j), minima (D.size, 3) and visited (_descend) are work space.
    A block can hold a sample nearer to q than the nearest coarse sample only if
    |coarse - q| - eta_rows[a] is below that distance: the coarse local minima (8
    neighbours) among such blocks (the MAX_COARSE_MINIMA nearest) and their neighbours
    descend on the full grid (_descend), and the distinct grid minima within eta_fine (mm)
    of the best are the seeds (at most S, the nearest)."""
    n_i, n_j = D.shape
    slab = np.maximum(np.maximum(z_rows[:, 0] - q[2], q[2] - z_rows[:, 1]), 0.0)  # z gap (mm) per row
    lowest = np.inf  # squared
    scanned = np.zeros(n_i, dtype=np.bool_)  # rows not scanned count as infinitely far
    for a in np.argsort(slab):
        if slab[a] ** 2 < lowest:  # else no sample of the row's blocks lies nearer
            scanned[a] = True
            for b in range(n_j):
                D[a, b] = _dist2(coarse, a, b, q)
                lowest = min(lowest, D[a, b])
    lowest = np.sqrt(lowest)
    n = 0
    for a in np.flatnonzero(scanned):
        limit = (lowest + eta_rows[a]) ** 2
        for b in range(n_j):
            if D[a, b] > limit:
                continue
            local_min = True
            for aa in range(max(a - 1, 0), min(a + 2, n_i)):
                for db in range(-1, 2):
                    local_min &= not scanned[aa] or D[aa, (b + db) % n_j] >= D[a, b]
            if local_min:  # (value, a, b)
                minima[n, 0], minima[n, 1], minima[n, 2] = D[a, b], a, b
                n += 1
    # each minimum and its coarse neighbours descend: a ridge of the distance between two
    # coarse samples (the pointed eye's crease) leaves a basin without a coarse minimum
    found = np.empty((9 * MAX_COARSE_MINIMA, 3))  # (i, j, squared distance) on the full grid
    n_found = 0
    for o in np.argsort(minima[:n, 0])[:MAX_COARSE_MINIMA]:
        a, b = int(minima[o, 1]), int(minima[o, 2])
        for aa in range(max(a - 1, 0), min(a + 2, n_i)):
            for db in range(-1, 2):
                bb = (b + db) % n_j
                if scanned[aa] and D[aa, bb] <= (lowest + eta_rows[aa]) ** 2:
                    i, j, d2 = _descend(P, q, k * aa + k // 2, k * bb + k // 2, k // 2, visited, stamp)
                    if i >= 0:
                        found[n_found, 0], found[n_found, 1], found[n_found, 2] = i, j, d2
                        n_found += 1
    order = np.argsort(found[:n_found, 2])
    best = np.sqrt(found[order[0], 2])
    count = 0
    for o in order:
        if count == seeds.shape[0] or np.sqrt(found[o, 2]) > best + eta_fine:
            break
        seen = False
        for c in range(count):
            seen |= seeds[c, 0] == found[o, 0] and seeds[c, 1] == found[o, 1]
        if not seen:
            seeds[count, 0], seeds[count, 1] = int(found[o, 0]), int(found[o, 1])
            count += 1
    return count


@njit  # not cached: loaded from numba's cache it ran 4-5x slower than compiled (~2 s, once a process)
def _closest_batch(kind, p, Q, P, U, coarse, eta_rows, z_rows, k, eta_fine, iterations):
    """(M, 3) closest surface points (mm) to Q (M, 3) mm: Levenberg-Marquardt from each
    seed of `_seeds` on the cloud P (n_theta, n_phi, 3) mm in the directions U (same
    shape), the nearest result."""
    X = np.empty_like(Q)
    D = np.empty(coarse.shape[:2])
    minima = np.empty((D.size, 3))
    seeds = np.empty((4, 2), dtype=np.int64)
    visited = np.zeros(P.shape[:2], dtype=np.int64)
    for m in range(Q.shape[0]):
        q = Q[m]
        best = np.inf
        for s in range(_seeds(P, coarse, eta_rows, z_rows, q, k, eta_fine, D, minima, seeds, visited, m + 1)):
            u = U[seeds[s, 0], seeds[s, 1]]
            Xs, cost = _closest_point(kind, p, q, (u[0], u[1], u[2]), iterations)
            if cost < best:
                best = cost
                X[m, 0], X[m, 1], X[m, 2] = Xs
    return X


@njit(cache=True)
def _distance_and_gradient(kind, p, Q, X):
    """((M,) signed distance mm, > 0 inside; (M, 3) unit gradient, inward) of Q (M, 3) mm
    with closest surface points X (M, 3) mm; within 1e-6 mm of the surface the gradient
    is the normal there."""
    sd, G = np.empty(Q.shape[0]), np.empty_like(Q)
    for m in range(Q.shape[0]):
        V = Q[m] - X[m]
        dist = np.sqrt(V @ V)
        sign = 1.0 if _inside_value(kind, p, Q[m, 0], Q[m, 1], Q[m, 2]) < 0.0 else -1.0
        sd[m] = sign * dist
        if dist > 1e-6:
            G[m] = sign * V / dist
        else:
            r = np.sqrt(X[m] @ X[m])
            u = (X[m, 0] / r, X[m, 1] / r, X[m, 2] / r) if r > 0.0 else (0.0, 0.0, -1.0)
            G[m] = _normal_inward(kind, p, u)
    return sd, G


class StarSurface:
    """Surface x = rho(u) u (mm) for unit directions u, about the origin of its frame.

    `rho` (a RadialFunction) must be positive and continuous; the region inside is
    {x : |x| < rho(x/|x|)}. `cloud_shape` sets the dense sampling used to seed
    closest-point searches (default ~0.08 mm spacing on an eye-sized surface).
    """

    def __init__(self, rho: RadialFunction, cloud_shape: tuple[int, int] = (400, 800)):
        if not isinstance(rho, RadialFunction):
            raise ValueError(f"rho must be a RadialFunction (one of {', '.join(RADIAL_KINDS)}), got {type(rho).__name__}")
        self.rho = rho
        self._cloud_shape = cloud_shape
        self._grid: tuple[np.ndarray, ...] | None = None
        self._constants: tuple[float, float, float] | None = None

    def points(self, U: np.ndarray) -> np.ndarray:
        """(M, 3) surface points (mm) in the directions U (M, 3), unit vectors."""
        return self.rho(U)[:, None] * U

    def inside_value(self, X: np.ndarray) -> np.ndarray:
        """(M,) |x| - rho(x/|x|) (mm) at the points X (M, 3) mm: < 0 inside, 0 on, > 0
        outside; the origin is inside (the compiled `_inside_value` the ray march uses)."""
        return _inside_values(self.rho.kind, self.rho.params, np.ascontiguousarray(as_points(X, "X")))

    def ray_cast(self, O: np.ndarray, D: np.ndarray, step_mm: float = MARCH_STEP_MM, t_max_mm: float = np.inf):
        """(M,) distance (mm) along unit rays D (M, 3) from O (M, 3) mm to the first crossing
        of the surface (from inside: the first exit), NaN when there is none within t_max_mm.

        Marches where the ray runs in the shell that holds the surface, in steps no shorter
        than `step_mm` and no longer than the slope bound allows (no crossing skipped; an
        excursion across the surface is found down to CLIP_MM deep), and refines the
        first sign change to ~1e-13 mm (Illinois regula falsi).
        """
        if not step_mm > 0.0:
            raise ValueError(f"step_mm must be > 0 mm, got {step_mm}")
        r_in, r_out, lip = self.march_constants()
        return _ray_hits(self.rho.kind, self.rho.params, np.ascontiguousarray(O, dtype=float),
                         np.ascontiguousarray(D, dtype=float), r_in, r_out, lip, float(step_mm), float(t_max_mm))

    def march_constants(self) -> tuple[float, float, float]:
        """(r_in mm, r_out mm, lip): the surface lies in the shell r_in <= |x| <= r_out, and
        along any unit ray in that shell the inside value changes by at most lip per mm.

        With S >= |grad rho| (mm/rad) on the unit sphere: |d|x|/dt| = |cos psi| and
        |d rho(u)/dt| <= S sin(psi) / |x| (psi: angle between ray and radius), so
        lip = sqrt(1 + (S / r_in)^2). S is the largest slope of rho between neighbours on
        a 180 x 360 (theta, phi) grid (the mean value theorem: each such quotient is a
        slope of rho), times SLOPE_SAFETY for what lies between samples; the eye shapes'
        features (the pointed crease, the staphyloma's 21 deg rim, the detached 24 deg
        bump) are 10-40 grid cells wide. r_in, r_out: the grid's extremes of rho widened
        by S times the grid's covering angle (< pi / 180)."""
        if self._constants is None:
            n_theta, n_phi = 180, 360
            theta = (np.arange(n_theta) + 0.5) * np.pi / n_theta
            phi = np.arange(n_phi) * 2.0 * np.pi / n_phi
            U = np.stack([np.outer(np.sin(theta), np.cos(phi)), np.outer(np.sin(theta), np.sin(phi)),
                          np.outer(np.cos(theta), np.ones(n_phi))], axis=-1)
            r = self.rho(U.reshape(-1, 3)).reshape(n_theta, n_phi)
            slope_theta = np.abs(np.diff(r, axis=0)) / (np.pi / n_theta)
            arc_phi = 2.0 * np.arcsin(np.sin(theta) * np.sin(np.pi / n_phi))[:, None]
            slope_phi = np.abs(np.roll(r, -1, axis=1) - r) / arc_phi
            S = SLOPE_SAFETY * float(np.sqrt(slope_theta**2 + slope_phi[:-1] ** 2).max())
            margin = S * np.pi / n_theta
            r_in, r_out = float(r.min()) - margin, float(r.max()) + margin
            if r_in <= 0.0:
                raise ValueError(f"the radial function must stay > {margin:.3g} mm (its slope times the grid's "
                                 f"spacing), got a minimum of {r.min():.3g} mm")
            self._constants = (r_in, r_out, float(np.sqrt(1.0 + (S / r_in) ** 2)))
        return self._constants

    def _cloud(self) -> tuple[np.ndarray, ...]:
        """(P, U, coarse, eta_rows, z_rows): the cloud's surface points P (n_theta, n_phi, 3)
        mm in the directions U (same shape), its coarse grid (the samples at the centres of
        its COARSE_STEP x COARSE_STEP blocks, (n_theta / k, n_phi / k, 3) mm) and, per row of
        blocks, the farthest (mm) a block's sample lies from its centre and the range of
        their z (min, max) mm."""
        if self._grid is None:
            n_theta, n_phi = self._cloud_shape
            U = unit_sphere_grid(n_theta, n_phi).reshape(n_theta, n_phi, 3)
            P = self.points(U.reshape(-1, 3)).reshape(U.shape)
            k = COARSE_STEP
            blocks = P[: n_theta // k * k, : n_phi // k * k].reshape(n_theta // k, k, n_phi // k, k, 3)
            coarse = np.ascontiguousarray(blocks[:, k // 2, :, k // 2])
            eta_rows = np.linalg.norm(blocks - coarse[:, None, :, None], axis=-1).max(axis=(1, 2, 3))
            z = blocks[..., 2].reshape(len(blocks), -1)
            self._grid = (P, U, coarse, eta_rows, np.column_stack([z.min(axis=1), z.max(axis=1)]))
        return self._grid

    def closest_point(self, Q: np.ndarray, iterations: int = 30) -> np.ndarray:
        """(M, 3) closest surface points (mm) to Q (M, 3) mm.

        Seeds from the cloud's local minima of the distance (`_seeds`), then minimises
        |x(a, b) - q|^2 over the local parametrisation x(a, b) = rho(u) u,
        u = normalise(u0 + a e1 + b e2), with Levenberg-Marquardt steps (finite-difference
        Jacobian, accepted only if they reduce the distance), so the result is never
        worse than the seed.
        """
        return _closest_batch(self.rho.kind, self.rho.params, np.ascontiguousarray(Q, dtype=float), *self._cloud(),
                              COARSE_STEP, SEED_TIE_MM, int(iterations))

    def normals_inward(self, U: np.ndarray) -> np.ndarray:
        """(M, 3) unit inward normals at the surface points in directions U (finite differences)."""
        return _normals_batch(self.rho.kind, self.rho.params, np.ascontiguousarray(U, dtype=float))

    def signed_distance_and_gradient(self, Q: np.ndarray):
        """((M,) signed distance mm, > 0 inside; (M, 3) unit gradient, pointing inward)."""
        Q = np.ascontiguousarray(Q, dtype=float)
        return _distance_and_gradient(self.rho.kind, self.rho.params, Q, self.closest_point(Q))
