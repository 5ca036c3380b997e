"""Star-shaped closed surfaces given by a radial function r = rho(u) about their centre: the
compiled family of radial functions of `RADIAL_KINDS`, their builders, and the surface's
geometry (inside value, tangent basis, point in a direction, inward normal).

The radial functions are one compiled family (numba caches a kernel per function, not
per closure, so the kinds share one set of kernels) with their parameters in a flat
array; models.eyes.catalog builds the eye shapes from them. Units: mm, rad; the frame of
the surface (E for the eyes).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from models.shapes.validation import as_positive, as_vector3

RADIAL_KINDS = ("ellipsoid", "pointed", "staphyloma", "detached")
_ELLIPSOID, _POINTED, _STAPHYLOMA, _DETACHED = range(len(RADIAL_KINDS))
RHO, INSIDE, NORMAL = range(3)  # the quantities of `per_row`


@njit(cache=True)
def rho(kind, p, x, y, z):
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
def inside_value(kind, p, x, y, z):
    """|x| - rho(x/|x|) (mm) at the point (x, y, z) mm; the origin counts as direction -z."""
    r = np.sqrt(x * x + y * y + z * z)
    if r > 0.0:
        return r - rho(kind, p, x / r, y / r, z / r)
    return -rho(kind, p, 0.0, 0.0, -1.0)


@njit(cache=True)
def tangent_basis(ux, uy, uz):
    """Two unit vectors (tuples) orthogonal to the unit (ux, uy, uz) and to each other."""
    hx, hy = (1.0, 0.0) if abs(ux) < 0.9 else (0.0, 1.0)  # helper (hx, hy, 0)
    e1x, e1y, e1z = -uz * hy, uz * hx, ux * hy - uy * hx  # u x helper
    n = np.sqrt(e1x * e1x + e1y * e1y + e1z * e1z)
    e1x, e1y, e1z = e1x / n, e1y / n, e1z / n
    return (e1x, e1y, e1z), (uy * e1z - uz * e1y, uz * e1x - ux * e1z, ux * e1y - uy * e1x)


@njit(cache=True)
def surface_at(kind, p, u, e1, e2, a, b):
    """The surface point (tuple, mm) in the direction normalise(u + a e1 + b e2)."""
    x, y, z = u[0] + a * e1[0] + b * e2[0], u[1] + a * e1[1] + b * e2[1], u[2] + a * e1[2] + b * e2[2]
    n = np.sqrt(x * x + y * y + z * z)
    x, y, z = x / n, y / n, z / n
    r = rho(kind, p, x, y, z)
    return r * x, r * y, r * z


@njit(cache=True)
def normal_inward(kind, p, u):
    """The unit inward normal (3,) at the surface point in the unit direction u (tuple)
    (finite differences of the parametrisation, 1e-6 rad)."""
    e1, e2 = tangent_basis(u[0], u[1], u[2])
    X = np.array(surface_at(kind, p, u, e1, e2, 0.0, 0.0))
    n = np.cross(np.array(surface_at(kind, p, u, e1, e2, 1e-6, 0.0)) - X,
                 np.array(surface_at(kind, p, u, e1, e2, 0.0, 1e-6)) - X)
    n /= np.linalg.norm(n)
    return -n if n @ X > 0.0 else n


@njit(cache=True)
def per_row(kind, p, X, quantity):
    """(M, 1) or (M, 3): `quantity` at each row of X (M, 3) for the radial function (kind,
    p): RHO, rho (mm) in the unit directions X; INSIDE, the inside value (mm) at the points
    X mm; NORMAL, the unit inward normal (M, 3) at the surface points in the unit
    directions X."""
    out = np.empty((X.shape[0], 3 if quantity == NORMAL else 1))
    for m in range(X.shape[0]):
        x, y, z = X[m, 0], X[m, 1], X[m, 2]
        if quantity == RHO:
            out[m, 0] = rho(kind, p, x, y, z)
        elif quantity == INSIDE:
            out[m, 0] = inside_value(kind, p, x, y, z)
        else:
            out[m] = normal_inward(kind, p, (x, y, z))
    return out


class RadialFunction(NamedTuple):
    """A radial function rho(u) (mm) of the kind RADIAL_KINDS[kind] with parameters
    `params` (see `rho`); call it on (M, 3) unit directions for (M,) radii in mm."""

    kind: int
    params: np.ndarray

    def __call__(self, U: np.ndarray) -> np.ndarray:
        return per_row(self.kind, self.params, np.ascontiguousarray(U, dtype=float), RHO)[:, 0]


def _with_base(radii, *extra) -> np.ndarray:
    """The parameters of `rho`: 1 / radii^2 (radii (3,) mm, each > 0), then `extra`."""
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
