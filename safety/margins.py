"""How much the boundary must allow for what the eye model does not know yet.

Before the model exists, a conservative prior bounds the motion: a sphere about the
nominal eye centre that lies inside every retina of the population we simulate
(the smallest semi-axis, hyperopic +4 D: 9.548 mm), less the placement uncertainty of
the nominal centre and a reserve. Once the model exists, the filter adds a margin to
d_safe that reflects its phase: in the sphere phase the sphere can be off by a
millimetre away from the scanned patch (the emmetropic sphere's MAE is 0.3 mm, its
worst point more), in the ellipsoid phase by a few times its residual.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models import Sphere
from models.shapes.validation import as_vector3, check_positive

SMALLEST_RETINAL_SEMI_AXIS_MM = 9.548  # hyperopic +4 D length semi-axis (models.eyes)


def conservative_prior(p_W_nominal_center, placement_uncertainty_mm: float = 1.0, reserve_mm: float = 0.5) -> Sphere:
    """The prior eye: a sphere about the nominal eye centre (W, mm) of radius
    9.548 - placement_uncertainty - reserve mm, inside every simulated retina."""
    r = SMALLEST_RETINAL_SEMI_AXIS_MM - placement_uncertainty_mm - reserve_mm
    if not (np.isfinite(r) and r > 1.0):
        raise ValueError(f"prior radius {r:.2f} mm: placement_uncertainty_mm + reserve_mm must stay below 8.5 mm")
    return Sphere(as_vector3(p_W_nominal_center, "p_W_nominal_center"), r)


@dataclass(frozen=True)
class UncertaintyMargins:
    """Extra clearance (mm) added to d_safe by model phase."""

    sphere_mm: float = 1.0
    ellipsoid_base_mm: float = 0.05
    ellipsoid_residual_factor: float = 3.0

    def __post_init__(self):
        check_positive(self, "sphere_mm", "ellipsoid_base_mm", "ellipsoid_residual_factor", allow_zero=True)

    def margin_mm(self, kind: str | None, residual_mm: float = 0.0) -> float:
        """Margin for a model of `kind` ("sphere", "ellipsoid", or None for the prior,
        which is conservative by construction) with RMS residual `residual_mm`."""
        if kind is None:
            return 0.0
        if kind == "sphere":
            return self.sphere_mm
        if kind == "ellipsoid":
            r = residual_mm if np.isfinite(residual_mm) else 0.0
            return self.ellipsoid_base_mm + self.ellipsoid_residual_factor * r
        raise ValueError(f"kind must be 'sphere', 'ellipsoid' or None, got {kind!r}")
