"""The pose X_WE of an eye: its frame E (design.md: origin at the centre of the retinal
ellipsoid, z = visual axis pointing anterior, x temporal, y superior) in W. Units: mm, rad."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from models.shapes.validation import as_rotation, as_vector3


def _rotation_about(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * K + (1 - np.cos(angle_rad)) * K @ K


@dataclass(frozen=True, eq=False)
class EyePose:
    """X_WE: rotation R_WE (3, 3) and position p_WE (3,) mm of the eye frame E in W."""

    R_WE: np.ndarray = field(default_factory=lambda: np.eye(3))
    p_WE: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        object.__setattr__(self, "R_WE", as_rotation(self.R_WE, "R_WE", tol=1e-8))
        object.__setattr__(self, "p_WE", as_vector3(self.p_WE, "p_WE"))

    @classmethod
    def anatomical(cls, tilt_deg: float = 11.0, nasal_mm: float = 0.5, inferior_mm: float = 0.2) -> EyePose:
        """A real eye's retinal ellipsoid (Atchison 2005): tilted `tilt_deg` about the
        vertical axis and decentred nasally (-x) and inferiorly (-y)."""
        return cls(_rotation_about(np.array([0.0, 1.0, 0.0]), np.radians(tilt_deg)), [-nasal_mm, -inferior_mm, 0.0])

    def to_E(self, P_W: np.ndarray) -> np.ndarray:
        return (P_W - self.p_WE) @ self.R_WE

    def to_W(self, P_E: np.ndarray) -> np.ndarray:
        return P_E @ self.R_WE.T + self.p_WE
