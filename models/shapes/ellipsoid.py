"""Ellipsoids: the frozen result type with exact signed distance (Eberly), a distance field
(models.shapes.field) with its compiled kernel, and the compiled beam cast on a placed
ellipsoid (`ellipsoid_hits`)."""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numba import njit

from models.shapes.ellipsoid_distance import closest_point_first_octant, ellipsoid_distance_and_gradient
from models.shapes.field import FieldKernel, exact_uncertainty, field_params
from models.shapes.rays import incidence_rad, rays_in_frame, unit_rays
from models.shapes.sphere import sample_quadric_surface
from models.shapes.validation import as_points, as_rotation, as_vector3


@dataclass(frozen=True, eq=False)
class Ellipsoid:
    """{x : (x - c)^T R diag(radii)^-2 R^T (x - c) = 1} in some frame (W or E).

    `center` (3,) mm; `radii` (3,) semi-axes in mm, > 0; `rotation` (3, 3) a proper
    rotation whose column i is the direction of semi-axis i in the same frame.
    Signed distances are > 0 inside (the vitreous side), 0 on the surface, < 0 outside.
    """

    center: np.ndarray
    radii: np.ndarray
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self):
        c = as_vector3(self.center, "center")
        r = as_vector3(self.radii, "radii")
        if min(r.tolist()) <= 0.0:  # finite (as_vector3): plain floats, cheaper than NumPy's any
            raise ValueError(f"radii must all be > 0 mm, got {r}")
        R = as_rotation(self.rotation, "rotation", tol=1e-8)
        self._hold(c, r, R)

    def _hold(self, center: np.ndarray, radii: np.ndarray, rotation: np.ndarray, copy: bool = True) -> None:
        """Keep the float arrays centre (3,), semi-axes (3,), rotation (3, 3) read-only: as
        copies, or (not `copy`) the given read-only arrays themselves."""
        for name, a in (("center", center), ("radii", radii), ("rotation", rotation)):
            if copy:
                a = a.copy()
                a.setflags(write=False)
            object.__setattr__(self, name, a)

    @classmethod
    def of_fit(cls, center: np.ndarray, radii: np.ndarray, rotation: np.ndarray) -> Ellipsoid:
        """The Ellipsoid of a successful fit's float arrays, in the frame of the fitted points
        (models.fit.quadric_kernels.quadric_parameters: centre (3,) mm, semi-axes (3,) mm > 0 from
        positive eigenvalues, the eigenvectors as a right-handed orthonormal rotation (3, 3)),
        without the constructor's checks, which such a fit passes by construction. The
        closed loop reads a new one after every update (EllipsoidFit.ellipsoid): this takes
        ~3 us, half of what the checked constructor takes; ~1 us when the three arrays are
        read-only, which it then holds as they are (a fit's are when no one writes to them
        or to their buffer: the per-packet update's, models.adaptive.model), else read-only copies."""
        ellipsoid = object.__new__(cls)
        ellipsoid._hold(center, radii, rotation,
                        copy=center.flags.writeable or radii.flags.writeable or rotation.flags.writeable)
        return ellipsoid

    def __deepcopy__(self, memo) -> Ellipsoid:
        return self  # immutable: a copy would only turn its read-only arrays writeable

    @property
    def volume(self) -> float:
        """Enclosed volume in mm^3."""
        return 4.0 / 3.0 * np.pi * float(np.prod(self.radii))

    def _to_sorted_octant(self, Q: np.ndarray):
        """Local coordinates with axes sorted by decreasing radius, reflected to the first octant."""
        order = np.argsort(-self.radii, kind="stable")
        L = (Q - self.center) @ self.rotation[:, order]
        signs = np.where(L < 0.0, -1.0, 1.0)
        return order, signs, np.abs(L)

    def closest_point(self, Q) -> np.ndarray:
        """(M, 3) exact closest surface points (mm) to points Q (M, 3) mm.

        Exact on the axes and at the centre (where the closest points are the two
        ends of the shortest axis; the + end is returned)."""
        Q = as_points(Q, "Q")
        order, signs, Y = self._to_sorted_octant(Q)
        X = closest_point_first_octant(self.radii[order], Y) * signs
        return self.center + X @ self.rotation[:, order].T

    def signed_distance(self, Q) -> np.ndarray:
        """(M,) exact signed distance (mm) of Q (M, 3) mm; > 0 inside."""
        return self.signed_distance_and_gradient(Q)[0]

    def gradient(self, Q) -> np.ndarray:
        """(M, 3) unit gradient of the signed distance: the inward normal at the closest point."""
        return self.signed_distance_and_gradient(Q)[1]

    def signed_distance_and_gradient(self, Q) -> tuple[np.ndarray, np.ndarray]:
        """((M,) signed distance mm, (M, 3) unit gradient) from one compiled closest-point
        search for every point (ellipsoid_distance_and_gradient)."""
        return ellipsoid_distance_and_gradient(self.center, self.rotation, self.radii, as_points(Q, "Q"))

    def uncertainty(self, Q) -> np.ndarray:
        """(M,) zeros (mm): the distance is exact (+inf for a non-finite point)."""
        return exact_uncertainty(np.ascontiguousarray(as_points(Q, "Q", allow_nonfinite=True)))

    def field_kernel(self) -> FieldKernel:
        """The compiled distance field (models.shapes.field): ellipsoid_field with params
        [center (3,) mm, rotation row-major (9,), radii (3,) mm]."""
        return FieldKernel(ellipsoid_field, self._field_params)

    @cached_property
    def _field_params(self) -> np.ndarray:
        return field_params(self.center, self.rotation, self.radii)

    def sample_surface(self, n_theta: int, n_phi: int, z_max: float | None = None) -> np.ndarray:
        """(n_theta * n_phi, 3) surface points, equal-area in direction (u_z and azimuth
        uniform, x = c + R diag(radii) u). `z_max` (mm, along the third axis from the
        centre) crops the top: the paper's anterior crop."""
        return sample_quadric_surface(self.radii, self.rotation, self.center, n_theta, n_phi, z_max)

    def ray_cast(self, origins, dirs) -> np.ndarray:
        """(M,) distance (mm) along unit rays to the surface: first hit from inside,
        first entry from outside; NaN where a ray misses."""
        O, D = unit_rays(origins, dirs)
        Lo = (O - self.center) @ self.rotation / self.radii
        Ld = D @ self.rotation / self.radii
        return _unit_sphere_roots(np.ascontiguousarray(Lo), np.ascontiguousarray(Ld))


@njit(cache=True)
def ellipsoid_field(params, P):
    """The FieldKernel kernel of an Ellipsoid, params [center (3,) mm, rotation row-major (9,),
    radii (3,) mm]: (h (M,) mm, g (M, 3), u (M,) mm) at the points P (M, 3) mm,
    ellipsoid_distance_and_gradient's (h, g)."""
    h, g = ellipsoid_distance_and_gradient(params[0:3], params[3:12].reshape(3, 3), params[12:15], P)
    return h, g, exact_uncertainty(P)


@njit(cache=True, error_model="numpy")
def _unit_sphere_root(o0, o1, o2, u0, u1, u2):
    """The parameter t of the ray o + t u at the unit sphere (the ellipsoid in coordinates
    scaled by its semi-axes, so t is in the ray's own units): the exit from inside, the
    first entry at t >= 0 from outside; NaN without one. The numerically stable roots
    q / a and c / q, q = -(b + sign(b) sqrt(b^2 - a c)); a NaN root (a ray tangent at its
    origin) makes both NaN. Ellipsoid.ray_cast's and ellipsoid_hits' root."""
    a = u0 * u0 + u1 * u1 + u2 * u2
    b = o0 * u0 + o1 * u1 + o2 * u2
    c = o0 * o0 + o1 * o1 + o2 * o2 - 1.0
    disc = b * b - a * c
    if not disc >= 0.0:
        return np.nan
    q = -(b + np.copysign(np.sqrt(disc), b))
    t1, t2 = q / a, c / q
    if t1 != t1 or t2 != t2:
        return np.nan
    if c < 0.0:
        return max(t1, t2)
    t = min(t1, t2)
    return t if t >= 0.0 else np.nan


@njit(cache=True)
def _unit_sphere_roots(O, U):
    """(M,) `_unit_sphere_root` of the rays (O[m], U[m]) (M, 3), in scaled coordinates."""
    out = np.empty(O.shape[0])
    for m in range(O.shape[0]):
        out[m] = _unit_sphere_root(O[m, 0], O[m, 1], O[m, 2], U[m, 0], U[m, 1], U[m, 2])
    return out


@njit(cache=True, error_model="numpy")
def ellipsoid_hits(O_W, U_W, p_WE, R_WE, radii):
    """((M,) distance mm along the unit rays (O_W[m], U_W[m]) (M, 3) in W to the ellipsoid
    with semi-axes `radii` (3,) mm centred at p_WE (3,) mm with axes R_WE (3, 3) (its frame
    E), NaN where a ray misses it or meets it only behind its origin; (M,) incidence rad
    between the ray and the surface normal at the hit, NaN without a hit). The roots of
    `Ellipsoid.ray_cast` (the first hit from inside, the first entry from outside) and its
    normal in one compiled pass: Eye.beam_hits of the ellipsoidal eyes. ValueError as
    models.shapes.rays.rays_in_frame."""
    M = O_W.shape[0]
    d, incidence = np.full(M, np.nan), np.full(M, np.nan)
    O_E, U_E = rays_in_frame(O_W, U_W, p_WE, R_WE)
    o, u = np.empty(3), np.empty(3)  # origin and direction in E, scaled by the semi-axes
    for m in range(M):
        for k in range(3):
            o[k], u[k] = O_E[m, k] / radii[k], U_E[m, k] / radii[k]
        t = _unit_sphere_root(o[0], o[1], o[2], u[0], u[1], u[2])
        if not t > 0.0:  # none, or only at the origin
            continue
        d[m] = t
        n2, nu = 0.0, 0.0  # the inward normal at the hit: -p_E / radii^2 = -(o + t u) / radii
        for k in range(3):
            n_k = -(o[k] + t * u[k]) / radii[k]
            n2 += n_k * n_k
            nu += n_k * u[k] * radii[k]
        incidence[m] = incidence_rad(nu, np.sqrt(n2))
    return d, incidence
