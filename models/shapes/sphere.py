"""Spheres: the frozen result type, a distance field (models.shapes.field) with its compiled
kernel, and the batch linear least-squares fit."""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numba import njit

from models.shapes.field import FieldKernel, exact_uncertainty, field_outputs, field_params
from models.shapes.rays import unit_rays
from models.shapes.sampling import unit_sphere_grid
from models.shapes.validation import as_points, as_positive, as_vector3


@njit(cache=True, inline="always")
def sphere_distance_one(center, radius, x0, x1, x2):
    """(signed distance mm, > 0 inside; the distance from the centre mm) of the point
    (x0, x1, x2) mm to the sphere (center, radius)."""
    v0, v1, v2 = center[0] - x0, center[1] - x1, center[2] - x2
    n = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    return radius - n, n


@njit(cache=True)
def sphere_distance_and_gradient(center, radius, Q):
    """((M,) signed distance mm, > 0 inside; (M, 3) unit gradient, the inward normal, +z
    at the centre by convention) of points Q (M, 3) mm to the sphere (center, radius); NaN
    for a non-finite point."""
    d, g, finite = field_outputs(Q)
    for m in range(Q.shape[0]):
        if not finite[m]:
            continue
        v0, v1, v2 = center[0] - Q[m, 0], center[1] - Q[m, 1], center[2] - Q[m, 2]
        d[m], n = sphere_distance_one(center, radius, Q[m, 0], Q[m, 1], Q[m, 2])
        if n == 0.0:
            g[m, 0], g[m, 1], g[m, 2] = 0.0, 0.0, 1.0
        else:
            g[m, 0], g[m, 1], g[m, 2] = v0 / n, v1 / n, v2 / n
    return d, g


@njit(cache=True)
def sphere_field(params, P):
    """The FieldKernel kernel of a Sphere, params [cx, cy, cz, r] (mm): (h (M,) mm, g (M, 3),
    u (M,) mm) at the points P (M, 3) mm, sphere_distance_and_gradient's (h, g)."""
    h, g = sphere_distance_and_gradient(params[0:3], params[3], P)
    return h, g, exact_uncertainty(P)


@dataclass(frozen=True, eq=False)
class Sphere:
    """A sphere in some frame (usually W or E): `center` (3,) mm, `radius` mm > 0.

    Signed distances are > 0 inside (the vitreous side), 0 on the surface, < 0 outside.
    """

    center: np.ndarray
    radius: float

    def __post_init__(self):
        c = as_vector3(self.center, "center")
        c.setflags(write=False)
        object.__setattr__(self, "center", c)
        object.__setattr__(self, "radius", as_positive(self.radius, "radius"))

    def __deepcopy__(self, memo) -> Sphere:
        return self  # immutable: a copy would only turn its read-only centre writeable

    @classmethod
    def of_fit(cls, center: np.ndarray, radius: float) -> Sphere:
        """The Sphere of a fit's centre (a float64 (3,) array of its own, which it then holds
        read-only) and radius mm, without the constructor's checks of the centre (the
        sphere filter makes a new one after every update: 0.8 us against 2.7 us); a radius
        that is not finite and > 0 goes to the checked constructor, which refuses it."""
        radius = float(radius)
        if not (0.0 < radius < np.inf and center.dtype == np.float64 and center.shape == (3,)
                and -np.inf < sum(center.tolist()) < np.inf):  # a NaN or an inf makes the sum one
            return cls(center, radius)
        sphere = object.__new__(cls)
        center.setflags(write=False)
        object.__setattr__(sphere, "center", center)
        object.__setattr__(sphere, "radius", radius)
        return sphere

    @property
    def volume(self) -> float:
        """Enclosed volume in mm^3."""
        return 4.0 / 3.0 * np.pi * self.radius**3

    def uncertainty(self, Q) -> np.ndarray:
        """(M,) zeros (mm): the distance is exact (+inf for a non-finite point)."""
        return exact_uncertainty(np.ascontiguousarray(as_points(Q, "Q", allow_nonfinite=True)))

    def field_kernel(self) -> FieldKernel:
        """The compiled distance field (models.shapes.field): sphere_field with params
        [cx, cy, cz, r] (mm)."""
        return FieldKernel(sphere_field, self._field_params)

    @cached_property
    def _field_params(self) -> np.ndarray:
        return field_params(self.center, self.radius)

    def signed_distance(self, Q) -> np.ndarray:
        """(M,) exact signed distance (mm) of points Q (M, 3) mm; > 0 inside."""
        return self.signed_distance_and_gradient(Q)[0]

    def gradient(self, Q) -> np.ndarray:
        """(M, 3) unit gradient of the signed distance: the inward surface normal
        at the closest point. At the centre (undefined) it is +z by convention."""
        return self.signed_distance_and_gradient(Q)[1]

    def signed_distance_and_gradient(self, Q) -> tuple[np.ndarray, np.ndarray]:
        """((M,) signed distance mm, (M, 3) unit gradient): both from one compiled pass."""
        return sphere_distance_and_gradient(self.center, float(self.radius), as_points(Q, "Q"))

    def ray_cast(self, origins, dirs) -> np.ndarray:
        """(M,) distance (mm) along unit rays to the sphere: first hit from inside, first
        entry from outside; NaN where a ray misses."""
        O, D = unit_rays(origins, dirs)
        V = O - self.center
        b = np.einsum("ij,ij->i", V, D)
        c = np.einsum("ij,ij->i", V, V) - self.radius**2
        with np.errstate(invalid="ignore"):
            sq = np.sqrt(b * b - c)
        t = np.where(c < 0.0, -b + sq, np.where(-b - sq >= 0.0, -b - sq, np.nan))
        return np.where(b * b - c >= 0.0, t, np.nan)

    def closest_point(self, Q) -> np.ndarray:
        """(M, 3) closest surface points (mm) to Q (M, 3); at the centre: the +z pole."""
        Q = as_points(Q, "Q")
        return self.center - self.radius * self.gradient(Q)

    def sample_surface(self, n_theta: int, n_phi: int, z_max: float | None = None) -> np.ndarray:
        """(n_theta * n_phi, 3) surface points on an equal-area grid (z uniform, phi uniform).

        `z_max` (mm, in this sphere's frame relative to its centre) crops the top:
        only points with z - center_z <= z_max are produced.
        """
        return sample_quadric_surface(np.full(3, self.radius), np.eye(3), self.center, n_theta, n_phi, z_max)


def sample_quadric_surface(radii, rotation, center, n_theta: int, n_phi: int, z_max=None) -> np.ndarray:
    """Equal-area-in-direction samples of an ellipsoid x = center + R diag(radii) u, |u| = 1.

    u comes from `unit_sphere_grid`; `z_max` (mm, along the third local axis from the
    centre) crops the anterior part: u_z <= z_max / radii[2]. Returns (n_theta * n_phi, 3) mm.
    """
    uz_max = 1.0 if z_max is None else float(np.clip(z_max / radii[2], -1.0 + 1e-12, 1.0))
    U = unit_sphere_grid(n_theta, n_phi, uz_max)
    return center + (U * radii) @ np.asarray(rotation).T


def fit_sphere(P) -> Sphere:
    """Linear least-squares sphere through points P (N >= 4, mm, any frame).

    Solves |p|^2 = 2 p.c + (r^2 - |c|^2) for (c, r^2 - |c|^2) with the points
    centred on their mean, which keeps the problem well conditioned far from the
    origin (e.g. in the robot base frame). Raises ValueError on fewer than 4
    points or coplanar points (no unique sphere).
    """
    P = as_points(P, "P")
    if len(P) < 4:
        raise ValueError(f"fit_sphere needs at least 4 points, got {len(P)}")
    p0 = P.mean(axis=0)
    X = P - p0
    H = np.column_stack([2.0 * X, np.ones(len(X))])
    z = np.einsum("ij,ij->i", X, X)
    sol, _, rank, sv = np.linalg.lstsq(H, z, rcond=None)
    if rank < 4 or sv[-1] < 1e-9 * sv[0]:
        raise ValueError("fit_sphere: points are coplanar or collinear; no unique sphere")
    c = sol[:3]
    r2 = sol[3] + c @ c
    if r2 <= 0:
        raise ValueError("fit_sphere: least-squares solution has no real radius")
    return Sphere(center=c + p0, radius=np.sqrt(r2))
