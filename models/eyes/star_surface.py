"""Closest points, signed distance and gradient on a star-shaped surface (models.eyes.radial),
and `StarSurface`, the composite eyes' retina in E.

The exact signed distance is seeded from the local minima of the distance over a dense
surface cloud, then refined by Levenberg-Marquardt on the surface parametrisation
(compiled with numba). Units: mm; the frame of the surface (E for the eyes).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models.eyes.radial import INSIDE, NORMAL, RADIAL_KINDS, RadialFunction, inside_value, normal_inward, per_row, surface_at, tangent_basis
from models.eyes.star_march import CLIP_MM, MARCH_STEP_MM, ray_hits
from models.shapes.sampling import unit_sphere_grid
from models.shapes.validation import as_points

COARSE_STEP = 8  # the closest-point search scans every 8th row and column of the cloud first
MAX_COARSE_MINIMA = 8  # coarse local minima refined per query, the nearest first
SEED_TIE_MM = 0.05  # cloud minima this close to the best are all refined (_seeds)
SLOPE_SAFETY = 2.0  # the sampled slope of rho times this bounds the true one (StarSurface.march_constants)


@njit(cache=True)
def _closest_point(kind, p, q, u0, iterations):
    """The closest surface point (tuple, mm) to q (3,) mm from the seed direction u0
    (tuple): Levenberg-Marquardt on (a, b) -> surface point in normalise(u0 + a e1 + b e2),
    finite-difference Jacobian, steps accepted only if they reduce the distance."""
    e1, e2 = tangent_basis(u0[0], u0[1], u0[2])
    a, b, lam, h = 0.0, 0.0, 1e-3, 1e-7
    X = surface_at(kind, p, u0, e1, e2, a, b)
    cost = (X[0] - q[0]) ** 2 + (X[1] - q[1]) ** 2 + (X[2] - q[2]) ** 2
    for _ in range(iterations):
        Xa = surface_at(kind, p, u0, e1, e2, a + h, b)
        Xb = surface_at(kind, p, u0, e1, e2, a, b + h)
        jaa, jab, jbb, ga, gb = 0.0, 0.0, 0.0, 0.0, 0.0
        for k in range(3):
            ja, jb, r = (Xa[k] - X[k]) / h, (Xb[k] - X[k]) / h, X[k] - q[k]
            jaa, jab, jbb, ga, gb = jaa + ja * ja, jab + ja * jb, jbb + jb * jb, ga + ja * r, gb + jb * r
        damp = lam * (jaa + jbb)  # lam (trace I + 1e-12), as a fraction of the curvature
        A00, A01, A11 = jaa + damp + lam * 1e-12, jab + lam * 1e-12, jbb + damp + lam * 1e-12
        det = A00 * A11 - A01 * A01
        step_a, step_b = -(A11 * ga - A01 * gb) / det, -(A00 * gb - A01 * ga) / det
        X_trial = surface_at(kind, p, u0, e1, e2, a + step_a, b + step_b)
        cost_trial = (X_trial[0] - q[0]) ** 2 + (X_trial[1] - q[1]) ** 2 + (X_trial[2] - q[2]) ** 2
        if cost_trial < cost:
            a, b, X, cost, lam = a + step_a, b + step_b, X_trial, cost_trial, lam * 0.3
        else:
            lam *= 10.0
        if max(abs(step_a), abs(step_b)) < 1e-12:
            break
    return X, cost


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
        sign = 1.0 if inside_value(kind, p, Q[m, 0], Q[m, 1], Q[m, 2]) < 0.0 else -1.0
        sd[m] = sign * dist
        if dist > 1e-6:
            G[m] = sign * V / dist
        else:
            r = np.sqrt(X[m] @ X[m])
            u = (X[m, 0] / r, X[m, 1] / r, X[m, 2] / r) if r > 0.0 else (0.0, 0.0, -1.0)
            G[m] = normal_inward(kind, p, u)
    return sd, G


class StarSurface:
    """Surface x = rho(u) u (mm) for unit directions u, about the origin of its frame.

    `rho` (a RadialFunction) must be positive and continuous; the region inside is
    {x : |x| < rho(x/|x|)}. `cloud_shape` sets the dense sampling that seeds the
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
        outside; the origin is inside (the compiled `inside_value` the ray march uses)."""
        return per_row(self.rho.kind, self.rho.params, np.ascontiguousarray(as_points(X, "X")), INSIDE)[:, 0]

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
        return ray_hits(self.rho.kind, self.rho.params, np.ascontiguousarray(O, dtype=float),
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
        return per_row(self.rho.kind, self.rho.params, np.ascontiguousarray(U, dtype=float), NORMAL)

    def signed_distance_and_gradient(self, Q: np.ndarray):
        """((M,) signed distance mm, > 0 inside; (M, 3) unit gradient, pointing inward)."""
        Q = np.ascontiguousarray(Q, dtype=float)
        return _distance_and_gradient(self.rho.kind, self.rho.params, Q, self.closest_point(Q))
