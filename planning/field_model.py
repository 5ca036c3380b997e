"""The retina as the planner must respect it: the safety filter's own distance field.

The filter keeps every watched point at h >= d_safe + k u + the calibration margin, with
h the field's signed distance (mm, > 0 inside the retina), u its uncertainty (mm: the
quadric phase's margin plus the misfit seen near measured directions, or the local
model's sigma) and k the barrier's sigma factor (safety.FilterConfig.sigma_factor). A
FieldModel gives the planner that rule as a shape: `signed_distance` is h - k u, the
clearance the barrier grants, compared with d_safe + the calibration margin
(BandSpec.boundary_mm); `ray_cast` and `gradient` are the model retina's (h = 0), where
the band's cells lie; `retina` the field's own h, for what must stay outside the eye.
So a plan and the filter that executes it share one definition of the boundary, and a
cell whose shaving target the field's uncertainty puts within reach of the boundary is
known before any motion. Units: mm; frame W.
"""
from __future__ import annotations

import numpy as np

RAY_BISECTIONS = 48  # halvings of the ray's bracket: 40 mm / 2^48 < 1e-12 mm
RAY_REACH_MM = 40.0  # rays from inside the eye leave every retina we simulate within this


class _Retina:
    """The field's own signed distance h (mm, > 0 inside) as a shape."""

    def __init__(self, field):
        self._field = field

    def signed_distance(self, P) -> np.ndarray:
        return np.asarray(self._field.signed_distance(np.asarray(P, dtype=float).reshape(-1, 3)), dtype=float)


class FieldModel:
    """`field` (models.shapes.field.DistanceField: signed_distance_gradient_uncertainty) with
    the barrier's `sigma_factor` k >= 0, as the shape the planner checks against; `kind`
    the model's ("sphere", "ellipsoid", "local", ...). `bound`: the field whose h - k u the
    filter's barrier keeps to, when it is not `field` itself (the local model's barrier,
    models.local.field.LocalField.with_fallback, answers the prior's bound where that is the
    larger: no retina, so the surface, its normals and u stay `field`'s)."""

    def __init__(self, field, sigma_factor: float, kind: str = "", bound=None):
        if not (np.isfinite(sigma_factor) and sigma_factor >= 0):
            raise ValueError(f"FieldModel.sigma_factor must be finite and >= 0, got {sigma_factor}")
        self.field, self.sigma_factor, self.kind = field, float(sigma_factor), kind
        self.bound = field if bound is None else bound
        self.retina = _Retina(field)

    def _hgu(self, P, field=None):
        return (self.field if field is None else field).signed_distance_gradient_uncertainty(
            np.ascontiguousarray(np.asarray(P, dtype=float).reshape(-1, 3)))

    def signed_distance(self, P) -> np.ndarray:
        """(M,) h - k u (mm) of the bound at P (M, 3): the clearance the filter's barrier grants there."""
        h, _, u = self._hgu(P, self.bound)
        return np.asarray(h, dtype=float) - self.sigma_factor * np.asarray(u, dtype=float)

    def uncertainty(self, P) -> np.ndarray:
        """(M,) u (mm) at P (M, 3)."""
        return np.asarray(self._hgu(P)[2], dtype=float)

    def gradient(self, P) -> np.ndarray:
        """(M, 3) the field's gradient (unit, inward) at P (M, 3)."""
        return np.asarray(self._hgu(P)[1], dtype=float)

    def ray_cast(self, origins, dirs) -> np.ndarray:
        """(M,) distance (mm) along unit rays dirs (M, 3) from origins (M, 3) inside the retina
        (h > 0) to the model retina (h = 0), by bisection on h over RAY_REACH_MM; NaN for a
        ray that starts outside or does not leave the retina within that reach."""
        O = np.asarray(origins, dtype=float).reshape(-1, 3)
        D = np.asarray(dirs, dtype=float).reshape(-1, 3)
        lo, hi = np.zeros(len(O)), np.full(len(O), RAY_REACH_MM)
        h = self.retina.signed_distance
        ok = (h(O) > 0) & (h(O + RAY_REACH_MM * D) < 0)
        for _ in range(RAY_BISECTIONS):
            mid = 0.5 * (lo + hi)
            inside = h(O + mid[:, None] * D) > 0
            lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
        return np.where(ok, 0.5 * (lo + hi), np.nan)


def retina_of(model):
    """The retina surface of a planning model: a FieldModel's field (h), a shape itself."""
    return model.retina if isinstance(model, FieldModel) else model


def least_uncertainty_mm(model, surface, standoff_mm: float) -> float:
    """k u (mm) least over the shaving targets `standoff_mm` inside the band `surface`
    (planning.peripheral.band_surface of `model`): what the filter's boundary adds to the
    spec's boundary_mm at the best cell (0 for a shape without uncertainty)."""
    if not isinstance(model, FieldModel):
        return 0.0
    _, _, S, N = surface
    T = (S + standoff_mm * N).reshape(-1, 3)
    return float(model.sigma_factor * np.min(model.uncertainty(T)))
