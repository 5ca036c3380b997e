"""The local-global retina model as a distance field (models.shapes.field): signed distance,
gradient and standard deviation of the retina surface r = R(u) about a fixed centre.

The distance is first order: F / |grad F| of F = R(u) - |p - c0|, exact on a sphere
about c0 and, elsewhere, off by about d^2 kappa / 2 at distance d from a surface of
curvature kappa (under 1 um at the model's errors of tens of um near the retina; 0.05 mm
at 1 mm on the pointed eye's crease). Within a few mm of c0 the tangential slope of R,
divided by |p - c0|, dominates grad F and the distance falls far below the true one (a
model of the spiral's first rings, 1.5 mm from c0: down to a fifth of it, on the safe
side); the barrier's form (with_fallback) takes the fallback sphere's bound there. The
uncertainty is the model's standard deviation at the point's direction
(models.local.grid), a one-sided bound once the barrier multiplies it
(safety.constraints.point_barrier: d_safe + k sigma).
Units: mm; points in the frame of the measured points (W in the loop).
"""
from __future__ import annotations

import numpy as np

from models.local.field_kernels import (BOUND, BOUND_SIZE, CAL, CAL_KNOTS_RAD, HEAD, N_CAL, PER_NODE, local_field,
                                        local_model_field, radii_at, unpack)
from models.local.kernels import global_params
from models.shapes.field import FieldKernel, KernelQueries
from models.shapes.sampling import unit_sphere_grid
from models.shapes.validation import as_points, as_vector3


class LocalField(KernelQueries):
    """A snapshot of a LocalRetinaModel (`model.params(local)`) as a distance field, and as
    a surface (`ray_cast`-free: `radius_and_sd`, `sample_surface`). `kind` "local" when the
    local correction is used, else the global model's kind ("sphere" | "ellipsoid").
    `barrier`: whether its answers are the barrier's form (with_fallback; params hold the
    bound) or the model alone (params may hold a bound all the same, which it ignores:
    local_model_field)."""

    def __init__(self, params: np.ndarray, kind: str = "local", barrier: bool = False):
        self.params = np.ascontiguousarray(params, dtype=float)
        p = self.params
        n = p[0] if p.ndim == 1 and len(p) >= HEAD else -1.0
        if not (n >= 0 and n == int(n) and len(p) == HEAD + int(n) * PER_NODE):
            raise ValueError(f"LocalField: params must be a LocalRetinaModel's params (1-D: {HEAD} numbers, then "
                             f"{PER_NODE} per node of its first number's count), got shape {np.shape(params)}")
        self.kind = kind
        self.barrier = bool(barrier)
        if self.barrier and not self.params[BOUND + 4] > 0.0:
            raise ValueError("LocalField: barrier=True needs params that hold a bound (fallback radius > 0)")
        self.center = np.array(self.params[3:6])

    @classmethod
    def exact(cls, shape, center) -> LocalField:
        """The global `shape` (Sphere or Ellipsoid) alone, exact (sd 0), seen from `center`
        (3,) mm (inside it): the conservative prior in the same field form; ValueError for a
        centre that is not a finite (3,) point inside the shape."""
        center = as_vector3(center, "center")
        if not float(shape.signed_distance(center[None])[0]) > 0.0:
            raise ValueError(f"LocalField.exact: center {center.tolist()} mm must lie inside the shape")
        head = np.concatenate([[0.0, np.radians(5.0), 1.0], center,
                               [0.02, 0.0, 0.0, 1.0, 1.0, 0.0, 1.0, 0.0], global_params(shape), np.ones(N_CAL),
                               np.zeros(BOUND_SIZE)])
        return cls(head, "prior")

    @classmethod
    def none(cls) -> LocalField:
        """No boundary: +inf everywhere."""
        head = np.zeros(HEAD)
        head[2] = -1.0
        return cls(head, "none")

    def with_fallback(self, sigma_factor: float, fallback, keep_mm: float, reach_mm: float = np.inf) -> LocalField:
        """The barrier's form: points answer the `fallback` Sphere (inside every retina)
        wherever it allows more than the model's h - sigma_factor x sigma, and their gradient
        elsewhere is that of h - sigma_factor x sigma, or, where that lies below `keep_mm`
        (the distance the filter keeps: d_safe and the calibration margin), of h (local_field);
        within `reach_mm` of keep_mm the bound is the lowest beside the point too (lateral_bound).
        It shares this field's params when they already hold that bound (bound_params; the
        loop's model system writes it, so the filter's step copies nothing), else it is a
        copy (~1 MB)."""
        bound = bound_params(sigma_factor, fallback, keep_mm, reach_mm)
        if np.array_equal(self.params[BOUND:HEAD], bound):
            return LocalField(self.params, self.kind, barrier=True)
        params = self.params.copy()
        params[BOUND:HEAD] = bound
        return LocalField(params, self.kind, barrier=True)

    def __deepcopy__(self, memo) -> LocalField:
        return self  # immutable by convention: its params are never written

    @property
    def sigma_calibration(self) -> dict:
        """The sd's calibration factors (models.local.calibration) at their angles from the
        data: {"gap_deg": [...], "factor": [...]} (JSON-ready)."""
        return {"gap_deg": [round(float(a), 3) for a in np.degrees(CAL_KNOTS_RAD)],
                "factor": [float(f) for f in self.params[CAL:CAL + N_CAL]]}

    def field_kernel(self) -> FieldKernel:
        """FieldKernel(local_field | local_model_field, params), as `barrier` says."""
        return FieldKernel(local_field if self.barrier else local_model_field, self.params)

    def signed_distance_gradient_uncertainty(self, P) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        Q = np.ascontiguousarray(as_points(P, "P", allow_nonfinite=True).reshape(-1, 3))
        return (local_field if self.barrier else local_model_field)(self.params, Q)

    def radius_and_sd(self, U) -> tuple[np.ndarray, np.ndarray]:
        """((M,) radius mm, (M,) sd mm) along unit directions U (M, 3) from the centre."""
        dirs, blend, local, c0, prior, gp, cal, x, cov, excess, has, near = unpack(self.params)
        U = np.ascontiguousarray(np.asarray(U, dtype=float).reshape(-1, 3))
        return radii_at(dirs, blend, local, c0, prior, gp, cal, x, cov, excess, has, near, U)

    def sample_surface(self, n_theta: int, n_phi: int, z_max=None) -> np.ndarray:
        """(n_theta * n_phi, 3) surface points (mm) along an equal-area grid of directions
        from the centre (`z_max` unsupported: the paper's crop is applied by the caller)."""
        U = unit_sphere_grid(n_theta, n_phi, 1.0)
        R, _ = self.radius_and_sd(U)
        return self.center + R[:, None] * U


def bound_params(sigma_factor: float, fallback, keep_mm: float, reach_mm: float = np.inf) -> np.ndarray:
    """The params' bound block (BOUND:HEAD) of the barrier's form: [k, fallback centre (3,)
    mm, fallback radius mm, keep_mm, reach_mm] for the barrier's `sigma_factor` k >= 0, a
    `fallback` Sphere, the distance `keep_mm` >= 0 the filter keeps besides k sigma and the
    barrier's reach past it, `reach_mm` > 0 (inf: everywhere), within which the bound
    looks beside the point too (field_kernels.lateral_bound)."""
    k, radius, keep, reach = float(sigma_factor), float(fallback.radius), float(keep_mm), float(reach_mm)
    if not (np.isfinite(k) and k >= 0.0 and np.isfinite(radius) and radius > 0.0 and np.isfinite(keep) and keep >= 0.0
            and reach > 0.0):
        raise ValueError(f"the barrier's bound needs sigma_factor >= 0, a fallback radius > 0 mm, keep_mm >= 0 and "
                         f"reach_mm > 0, got {k}, {radius}, {keep}, {reach}")
    return np.array([k, *np.asarray(fallback.center, dtype=float), radius, keep, reach])


class FieldValues:
    """A field's answers at a few points, as a shape: `signed_distance(Q)` and
    `gradient(Q)` give the stored values for the rows of Q equal to a stored point (NaN
    for others). What a run log holds of the local model per filter step (its nodes are
    ~1 MB), enough to replay the step. points (M, 3) mm, h (M,) mm, g (M, 3)."""

    def __init__(self, points, h, g):
        self.points = np.array(points, dtype=float).reshape(-1, 3)
        self.h = np.array(h, dtype=float).reshape(-1)
        self.g = np.array(g, dtype=float).reshape(-1, 3)
        if not (len(self.points) == len(self.h) == len(self.g)):
            raise ValueError(f"FieldValues: {len(self.points)} points, {len(self.h)} distances, {len(self.g)} gradients")

    def __deepcopy__(self, memo) -> FieldValues:
        return self

    def signed_distance_and_gradient(self, Q) -> tuple[np.ndarray, np.ndarray]:
        Q = np.asarray(Q, dtype=float).reshape(-1, 3)
        h, g = np.full(len(Q), np.nan), np.full((len(Q), 3), np.nan)
        for i, q in enumerate(Q):
            match = np.flatnonzero((self.points == q).all(axis=1))
            if len(match):
                h[i], g[i] = self.h[match[0]], self.g[match[0]]
        return h, g

    def signed_distance(self, Q) -> np.ndarray:
        return self.signed_distance_and_gradient(Q)[0]

    def gradient(self, Q) -> np.ndarray:
        return self.signed_distance_and_gradient(Q)[1]
