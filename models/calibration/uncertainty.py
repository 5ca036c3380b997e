"""How well the plate calibration knows the sensor pose: its standard errors from the fit.

At the fitted pose the residuals are linear in small changes of x = [p (3), u (3), a (3),
d] restricted to |u| = |a| = 1 (8 degrees of freedom: p, two for u, two for a, d). With
the residual Jacobian J on that tangent space and the residual variance s^2 = |r|^2 /
(N - 8), the covariance of the estimate is s^2 (J^T J)^-1 (Gauss-Newton, the noise
independent and of one size). From it: the sensor origin's standard error along the
beam and across it (mm) and the beam direction's (deg, the two tangent angles
combined). Units: mm, deg.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.calibration.plate import CalibrationResult, _as_flange_poses, _PlateProblem


@dataclass(frozen=True)
class CalibrationUncertainty:
    """Standard errors of the calibrated sensor pose: origin along and across the beam
    (mm), beam direction (deg)."""

    along_mm: float
    across_mm: float
    direction_deg: float

    @property
    def position_mm(self) -> float:
        """The origin's standard error in all (mm)."""
        return float(np.hypot(self.along_mm, self.across_mm))

    def bound(self, k: float = 3.0) -> tuple[float, float]:
        """(mm, deg): k standard errors of the origin and of the direction, a declared
        calibration bound (safety's `calibration_bound`)."""
        return k * self.position_mm, k * self.direction_deg


def _tangent(v: np.ndarray) -> np.ndarray:
    """(3, 2): two unit vectors spanning the plane perpendicular to the unit vector v."""
    e = np.eye(3)[np.argmin(np.abs(v))]
    t1 = np.cross(v, e)
    t1 /= np.linalg.norm(t1)
    return np.column_stack([t1, np.cross(v, t1)])


def calibration_uncertainty(R_WF, p_WF, distances_mm, result: CalibrationResult) -> CalibrationUncertainty:
    """The standard errors of `result` (calibrate_sensor on these flange poses (N, 3, 3),
    (N, 3) mm and distances (N,) mm), module docstring."""
    R, t = _as_flange_poses(R_WF, p_WF)
    m = np.asarray(distances_mm, dtype=float)
    problem = _PlateProblem(R, t, m)
    a = result.plane.normal_W
    u = result.sensor.u_F
    x = np.concatenate([result.sensor.p_FS, u, a, [result.plane.offset_mm + a @ problem.centre]])
    P = np.zeros((10, 8))
    P[0:3, 0:3] = np.eye(3)
    P[3:6, 3:5] = _tangent(u)
    P[6:9, 5:7] = _tangent(a)
    P[9, 7] = 1.0
    Jt = problem.jacobian(x) @ P
    r = problem.residuals(x)
    s2 = float(r @ r) / max(len(r) - 8, 1)
    C = s2 * np.linalg.inv(Jt.T @ Jt)
    Cp = C[0:3, 0:3]
    along2 = float(u @ Cp @ u)
    across2 = max(float(np.trace(Cp)) - along2, 0.0)
    direction = float(np.sqrt(max(np.trace(C[3:5, 3:5]), 0.0)))
    return CalibrationUncertainty(float(np.sqrt(along2)), float(np.sqrt(across2)), float(np.degrees(direction)))
