"""The eye model as the safety filter sees it: a distance field with uncertainty.

The adaptive model's current shape (a sphere or an ellipsoid) answers the signed
distance; how much it may overstate it (its uncertainty, mm) is the model phase's margin
plus, near measured directions, the misfit measured there (how far inside the shape the
retina was seen within `misfit_angle_rad`: a detachment that a sphere averages away).
Where a point lies further than `trust_angle_rad` from every measured direction, the
fit is an extrapolation, only as good as the eye is regular: with `fallback` given, the
point's distance is the smaller of the shape's and the fallback's (a sphere inside every
plausible retina: the conservative prior). Directions are seen from the coverage's
centre (models.adaptive.coverage).

`ModelField.none()` is a field without a boundary (+inf everywhere): what a barrier
reads where no model bounds its points yet.

Units: mm, rad; points in the frame of the shape (W in the loop).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models.adaptive.coverage_kernels import nearest_and_worst
from models.shapes.ellipsoid import Ellipsoid
from models.shapes.ellipsoid_distance import ellipsoid_distance_and_gradient
from models.shapes.field import FieldKernel, KernelQueries, unanswered
from models.shapes.sphere import Sphere, sphere_distance_and_gradient
from models.shapes.validation import as_points

NONE, SPHERE, ELLIPSOID = 0, 1, 2
# params: kind, centre (3), rotation (9), radii (3), margin, fallback (0/1), fallback centre (3), fallback radius,
# coverage (0/1), coverage centre (3), trust angle, cos(misfit angle), z band chord, covered count, then the
# covered directions (3 N) and their misfits (N)
_HEAD = 1 + 3 + 9 + 3 + 1 + 1 + 3 + 1 + 1 + 3 + 3 + 1  # 30


@njit(cache=True)
def coverage_trust(fp, P):
    """((M,) trusted flags, (M,) measured misfit mm) of the points P (M, 3) mm under the
    field packed in fp (ModelField): trusted within the trust angle of a measured
    direction, the misfit the largest measured within the misfit angle (the z band of
    the packed chord scanned). Without coverage: all trusted, no misfit."""
    M = P.shape[0]
    if fp[0] == NONE or fp[22] == 0.0:
        return np.ones(M, dtype=np.bool_), np.zeros(M)
    n = int(fp[29])
    dirs, misfit = fp[_HEAD:_HEAD + 3 * n].reshape((n, 3)), fp[_HEAD + 3 * n:_HEAD + 4 * n]
    V = np.empty((M, 3))
    for i in range(M):
        v0, v1, v2 = P[i, 0] - fp[23], P[i, 1] - fp[24], P[i, 2] - fp[25]
        norm = max(np.sqrt(v0 * v0 + v1 * v1 + v2 * v2), 1e-12)
        V[i, 0], V[i, 1], V[i, 2] = v0 / norm, v1 / norm, v2 / norm
    best, worst = nearest_and_worst(V, dirs, misfit, fp[27], fp[28])
    trusted = np.empty(M, dtype=np.bool_)
    for i in range(M):
        trusted[i] = np.arccos(min(max(best[i], -1.0), 1.0)) <= fp[26]
    return trusted, worst


@njit(cache=True)
def model_field_kernel(fp, P):
    """(h (M,) mm, grad (M, 3), u (M,) mm) of the field packed in fp (ModelField) at P (M, 3)
    mm; NaN, NaN and +inf at a non-finite point."""
    M = P.shape[0]
    kind = int(fp[0])
    if kind == NONE:
        return unanswered(P, np.full(M, np.inf), np.zeros((M, 3)), np.zeros(M))
    center, rotation, radii = fp[1:4], fp[4:13].reshape((3, 3)), fp[13:16]
    if kind == ELLIPSOID:
        h, g = ellipsoid_distance_and_gradient(center, rotation, radii, P)
    else:
        h, g = sphere_distance_and_gradient(center, radii[0], P)
    margin, fallback, has_coverage = fp[16], fp[17] != 0.0, fp[22] != 0.0
    u = np.full(M, margin)
    if not has_coverage:
        return unanswered(P, h, g, u)
    trusted, worst = coverage_trust(fp, P)
    for i in range(M):
        u[i] = margin + worst[i]
    if fallback:
        h_f, g_f = sphere_distance_and_gradient(fp[18:21], fp[21], P)
        for i in range(M):
            if not trusted[i] and h_f[i] < h[i]:
                h[i] = h_f[i]
                g[i, 0], g[i, 1], g[i, 2] = g_f[i, 0], g_f[i, 1], g_f[i, 2]
    return unanswered(P, h, g, u)


class ModelField(KernelQueries):
    """A model shape with its margin and coverage, as a distance field (mm, rad).

    `shape`: a models.Sphere or models.Ellipsoid (None: no boundary); `margin_mm` >= 0;
    `coverage`: a models.adaptive.coverage.CoverageView (None: no measured directions known, so no
    misfit and every point trusted); `fallback`: a Sphere for the untrusted points;
    `trust_angle_rad`, `misfit_angle_rad` in (0, pi]."""

    def __init__(self, shape, margin_mm: float = 0.0, coverage=None, fallback=None, trust_angle_rad: float = np.pi,
                 misfit_angle_rad: float = np.radians(10.0), band_chord: float = 2.0):
        if not (np.isfinite(margin_mm) and margin_mm >= 0):
            raise ValueError(f"ModelField.margin_mm must be finite and >= 0 mm, got {margin_mm}")
        if not (shape is None or isinstance(shape, (Sphere, Ellipsoid))):
            raise ValueError(f"ModelField.shape must be a models.Sphere, a models.Ellipsoid or None, got {type(shape).__name__}")
        for name, angle in (("trust_angle_rad", trust_angle_rad), ("misfit_angle_rad", misfit_angle_rad)):
            if not (0.0 < angle <= np.pi):
                raise ValueError(f"ModelField.{name} must be in (0, pi] rad, got {angle}")
        self.shape, self.margin_mm, self.coverage, self.fallback = shape, float(margin_mm), coverage, fallback
        head = np.zeros(_HEAD)
        if shape is not None:
            if hasattr(shape, "radii"):
                head[0], head[1:4], head[4:13], head[13:16] = ELLIPSOID, shape.center, shape.rotation.ravel(), shape.radii
            else:
                head[0], head[1:4], head[4:13], head[13:16] = SPHERE, shape.center, np.eye(3).ravel(), shape.radius
        head[16] = margin_mm
        if fallback is not None:
            head[17], head[18:21], head[21] = 1.0, fallback.center, fallback.radius
        parts = [head]
        if coverage is not None and shape is not None:
            dirs = coverage.sorted_directions
            misfit = coverage.misfits_mm
            head[22], head[23:26], head[26:29], head[29] = 1.0, coverage.center_W, (
                trust_angle_rad, np.cos(misfit_angle_rad), band_chord), len(dirs)
            parts += [np.asarray(dirs, dtype=float).ravel(),
                      np.zeros(len(dirs)) if misfit is None else np.asarray(misfit, dtype=float)]
        self.params = np.ascontiguousarray(np.concatenate(parts), dtype=float)

    def without_fallback(self) -> ModelField:
        """The same field with no fallback: every point's distance is the shape's."""
        field = object.__new__(ModelField)
        field.shape, field.margin_mm, field.coverage, field.fallback = self.shape, self.margin_mm, self.coverage, None
        field.params = self.params.copy()
        field.params[17] = 0.0
        return field

    @classmethod
    def none(cls) -> ModelField:
        """No boundary: +inf everywhere."""
        return cls(None)

    def trust(self, P) -> tuple[np.ndarray, np.ndarray]:
        """((M,) trusted flags, (M,) measured misfit mm) at P (M, 3) mm: what the field's
        distance and uncertainty used (coverage_trust)."""
        return coverage_trust(self.params, np.ascontiguousarray(as_points(P, "P", allow_nonfinite=True)))

    def field_kernel(self) -> FieldKernel:
        """FieldKernel(model_field_kernel, this field's packed parameters) (models.shapes.field)."""
        return FieldKernel(model_field_kernel, self.params)

    def signed_distance_gradient_uncertainty(self, P) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """((M,) mm, (M, 3), (M,) mm) at P (M, 3) mm."""
        return model_field_kernel(self.params, np.ascontiguousarray(as_points(P, "P", allow_nonfinite=True)))

