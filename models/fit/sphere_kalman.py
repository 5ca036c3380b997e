"""Online sphere fit: a Kalman filter on the linear sphere model (after Cornelissen et al.).

Measurement model: |p|^2 = [2x, 2y, 2z, 1] . [cx, cy, cz, r^2 - |c|^2] + noise, in
coordinates centred on the first point and divided by LENGTH_SCALE_MM. The state is
static (no process noise), so the filter is run in information form
(Y += h h^T / R, y += h z / R): algebraically the covariance-form Kalman filter
started from an uninformative prior, and exactly the batch least-squares solution
on the same points at every step, with no prior to tune and no loss of precision.
"""
from __future__ import annotations

import numpy as np

from models.fit.ellipsoid_fit import LENGTH_SCALE_MM
from models.fit.sphere_kernels import sphere_absorb, sphere_center_radius
from models.shapes.sphere import Sphere
from models.shapes.validation import as_points


class SphereKalmanFilter:
    """Sphere estimate that absorbs points one at a time at O(1) cost each.

    `update(P)` takes finite points (N, 3) mm in any frame; `sphere` is the current
    estimate (None until 4 non-coplanar points are in), made once per change of the state
    (which changes only when the filter takes points: `absorb`, `took`); `state` is the
    filter state [cx, cy, cz, r^2 - |c|^2] in scaled coordinates, `information` its 4x4
    information matrix (inverse covariance, in units of the measurement noise variance)
    and `information_vector` (4,) the information-form right-hand side
    (models.fit.sphere_kernels.sphere_absorb).
    """

    def __init__(self):
        self.information = np.zeros((4, 4))
        self.information_vector = np.zeros(4)
        self.p0: np.ndarray | None = None
        self.n_points = 0
        self.state: np.ndarray | None = None
        self._sphere: Sphere | None = None  # the Sphere of `state`, made on first use

    def update(self, P) -> None:
        """Absorb points P (N, 3) mm and refresh the state estimate."""
        self.absorb(as_points(P, "P"))

    def absorb(self, P: np.ndarray) -> None:
        """`update` for points already checked to be a finite (N, 3) float array."""
        if len(P) == 0:
            return
        if self.p0 is None:
            self.p0 = P[0].copy()
        x, ok = sphere_absorb(self.information, self.information_vector, P, self.p0, LENGTH_SCALE_MM,
                              self.n_points + len(P))
        self.took(len(P), x if ok else None)

    def took(self, k: int, state: np.ndarray | None) -> None:
        """Count k points that a caller has absorbed into `information` and
        `information_vector` itself (sphere_absorb about p0 with LENGTH_SCALE_MM:
        models.adaptive.update_kernel.packet_update), with the state they give (None: not yet determined)."""
        self.n_points += k
        self.state = state
        self._sphere = None

    @property
    def center_radius(self) -> tuple[np.ndarray, float] | None:
        """(center (3,) mm, radius mm) of the current estimate, or None."""
        if self.state is None:
            return None
        center = np.empty(3)
        return center, sphere_center_radius(self.state, self.p0, LENGTH_SCALE_MM, center)

    @property
    def sphere(self) -> Sphere | None:
        """The current Sphere estimate (mm, frame of the points), or None; the same object
        until the filter takes points."""
        if self._sphere is None and self.state is not None:
            self._sphere = Sphere.of_fit(*self.center_radius)
        return self._sphere
