"""Ground-truth eye shapes (the retina), placeable at any pose.

Frame E (design.md): origin at the centre of the retinal ellipsoid, z = visual axis
pointing anterior, x horizontal (+x temporal), y vertical (+y superior). Every shape
is a closed surface about the E origin; `make_eye(name, X_WE)` places it in W.
Composite shapes are star-shaped about the origin by construction, so they have no
overhangs, and their radial functions are continuous (no cracks).
"""
from __future__ import annotations

from functools import cached_property

import numpy as np
from numba import njit

from models.eyes.pose import EyePose
from models.eyes.radial import RadialFunction, ellipsoid_radial
from models.eyes.star_march import MARCH_STEP_MM, star_hits
from models.eyes.star_surface import StarSurface
from models.shapes.ellipsoid import Ellipsoid, ellipsoid_hits
from models.shapes.field import FieldKernel, exact_uncertainty
from models.shapes.rays import as_rays, unit_rays
from models.shapes.validation import as_points

ANTERIOR_CROP_MM = 5.0  # the paper's metrics ignore the anterior 5 mm along the visual axis


ELLIPSOIDAL_RETINA = -1  # retina_hits' kind of the ellipsoidal eyes (the composite ones: their RADIAL_KINDS index)
_UNUSED_PARAMS, _UNUSED_MARCH = np.empty(0), (0.0, 0.0, 0.0, 0.0)  # retina_hits' params and march for them


@njit(cache=True)
def retina_hits(O_W, U_W, p_WE, R_WE, radii, kind, params, march):
    """((M,) distance mm along the unit rays with origins O_W (M, 3) mm and directions U_W
    (M, 3) in W to the retina of an eye placed at (R_WE (3, 3), p_WE (3,) mm), NaN without
    a hit or with one only at or behind the origin; (M,) incidence rad between the ray and
    the retina's normal at the hit, NaN without a hit). kind ELLIPSOIDAL_RETINA: the
    ellipsoid with semi-axes radii (3,) mm (ellipsoid_hits, closed form; params and march
    unused); else the star-shaped retina of the radial function (kind, params)
    (star_hits, march = (r_in mm, r_out mm, lip, step mm)). Eye.beam_hits's kernel, which
    other compiled code calls with the eye's `Eye.hit_arguments` (the sensor's packet).
    ValueError as models.shapes.rays.rays_in_frame."""
    if kind == ELLIPSOIDAL_RETINA:
        return ellipsoid_hits(O_W, U_W, p_WE, R_WE, radii)
    return star_hits(kind, params, O_W, U_W, p_WE, R_WE, march[0], march[1], march[2], march[3])


class Eye:
    """A ground-truth retina placed at X_WE. All points and directions are in W, mm.

    `signed_distance(Q)` > 0 inside (vitreous side); `ray_cast(origins, dirs)` is the
    distance along unit rays to the first crossing of the retina (exact for the
    ellipsoidal shapes, bisected to well under 1 um for the composite ones).
    """

    def __init__(self, name: str, radii: np.ndarray, pose: EyePose, rho: RadialFunction | None = None):
        self.name = name
        self.radii = np.asarray(radii, dtype=float)
        self.pose = pose
        self.anterior_z_mm = float(self.radii[2])  # every shape keeps the ellipsoid's front
        self._ellipsoid_E = Ellipsoid(np.zeros(3), self.radii)
        self._star = None if rho is None else StarSurface(rho)

    @property
    def ellipsoid(self) -> Ellipsoid:
        """The retinal ellipsoid (for composite shapes: the one they are built on) in W."""
        return Ellipsoid(self.pose.p_WE, self.radii, self.pose.R_WE)

    def ray_cast(self, origins, dirs) -> np.ndarray:
        """(M,) distance (mm) along unit directions `dirs` from `origins` to the retina."""
        O_W, D_W = unit_rays(origins, dirs)
        O, D = self.pose.to_E(O_W), D_W @ self.pose.R_WE
        if self._star is None:
            return self._ellipsoid_E.ray_cast(O, D)
        return self._star.ray_cast(O, D)

    @property
    def hit_arguments(self) -> tuple:
        """(p_WE (3,) mm, R_WE (3, 3), radii (3,) mm, kind, params, march): the arguments of
        `retina_hits` after the rays for this eye (kind ELLIPSOIDAL_RETINA for the
        ellipsoidal eyes, else the radial function's kind and parameters with the march
        constants of its StarSurface and the march's shortest step)."""
        if self._star is None:
            return self.pose.p_WE, self.pose.R_WE, self.radii, ELLIPSOIDAL_RETINA, _UNUSED_PARAMS, _UNUSED_MARCH
        return (self.pose.p_WE, self.pose.R_WE, self.radii, self._star.rho.kind, self._star.rho.params,
                (*self._star.march_constants(), MARCH_STEP_MM))

    def beam_hits(self, O_W, U_W) -> tuple[np.ndarray, np.ndarray]:
        """((M,) distance mm along the unit rays with origins O_W (M, 3) mm and directions
        U_W (M, 3) in W to the retina (`ray_cast`'s), NaN without a hit or with one only at
        or behind the origin; (M,) incidence rad between the ray and the retina's normal
        (`surface_normal`) at the hit, NaN without a hit). One compiled call for any shape
        (`retina_hits`). ValueError for shapes other than (M, 3), a non-finite origin or a
        direction not of unit length."""
        return retina_hits(*as_rays(O_W, U_W), *self.hit_arguments)

    def signed_distance(self, Q) -> np.ndarray:
        """(M,) signed distance (mm) of Q (M, 3) in W to the retina; > 0 inside."""
        return self.signed_distance_and_gradient(Q)[0]

    def gradient(self, Q) -> np.ndarray:
        """(M, 3) unit gradient of the signed distance in W (inward at the closest point)."""
        return self.signed_distance_and_gradient(Q)[1]

    def signed_distance_and_gradient(self, Q) -> tuple[np.ndarray, np.ndarray]:
        """((M,) signed distance mm, > 0 inside; (M, 3) unit gradient in W) of Q (M, 3) in W,
        from one closest-point search in E."""
        Q_E = self.pose.to_E(as_points(Q, "Q"))
        shape = self._ellipsoid_E if self._star is None else self._star
        d, g = shape.signed_distance_and_gradient(Q_E)
        return d, g @ self.pose.R_WE.T

    def uncertainty(self, Q) -> np.ndarray:
        """(M,) zeros (mm): the distance is exact (+inf for a non-finite point)."""
        return exact_uncertainty(np.ascontiguousarray(as_points(Q, "Q", allow_nonfinite=True)))

    def field_kernel(self) -> FieldKernel:
        """The compiled distance field in W (models.shapes.field) of an ellipsoidal eye: its
        retinal ellipsoid's (`ellipsoid`), equal to this eye's methods to rounding (they
        take the points to E first). TypeError for a composite eye: its closest-point
        search runs on a surface cloud with no compiled form as one parameter array, so
        callers use the methods."""
        if self._star is not None:
            raise TypeError(f"the {self.name} eye has no compiled distance field: its closest-point search needs "
                            "its surface cloud; use signed_distance_and_gradient")
        return self._ellipsoid_W.field_kernel()

    @cached_property
    def _ellipsoid_W(self) -> Ellipsoid:
        return self.ellipsoid

    def surface_normal(self, P_W) -> np.ndarray:
        """(M, 3) unit inward normals in W at retina points P_W (M, 3) (points on the
        surface, e.g. ray hits; off the surface: the normal of the radial projection)."""
        P_E = self.pose.to_E(as_points(P_W, "P_W"))
        if self._star is None:
            n = -P_E / self.radii**2
            n /= np.linalg.norm(n, axis=1, keepdims=True)
        else:
            n = self._star.normals_inward(P_E / np.linalg.norm(P_E, axis=1, keepdims=True))
        return n @ self.pose.R_WE.T

    def surface_points(self, U_E: np.ndarray) -> np.ndarray:
        """(M, 3) retina points in W in the E-frame unit directions U_E (M, 3) from the centre."""
        rho = ellipsoid_radial(self.radii) if self._star is None else self._star.rho
        return self.pose.to_W(rho(U_E)[:, None] * U_E)

    def in_reference_region(self, P_W, crop_mm: float = ANTERIOR_CROP_MM) -> np.ndarray:
        """(M,) bool: points no further anterior than `crop_mm` behind the front of the eye."""
        return self.pose.to_E(as_points(P_W, "P_W"))[:, 2] <= self.anterior_z_mm - crop_mm

    def reference_samples(self, n_theta: int = 500, n_phi: int = 500, crop_mm: float = ANTERIOR_CROP_MM):
        """The paper's ground-truth sampling in W: n_theta x n_phi points (equal-area in
        direction) over the retina with the anterior `crop_mm` removed."""
        P_E = self._ellipsoid_E.sample_surface(n_theta, n_phi, z_max=self.anterior_z_mm - crop_mm)
        U = P_E / np.linalg.norm(P_E, axis=1, keepdims=True)
        return self.surface_points(U)
