"""The paper's Archimedean scan spiral, sampled at equal arc length."""
from __future__ import annotations

import numpy as np

from models.shapes.validation import as_positive


def _arc_length(theta: np.ndarray, b: float) -> np.ndarray:
    """Arc length (mm) of r = b theta / (2 pi) from 0 to theta (rad)."""
    a = b / (2.0 * np.pi)
    return 0.5 * a * (theta * np.sqrt(1.0 + theta**2) + np.arcsinh(theta))


PAPER_PITCH_MM = 0.5  # the paper's spiral: pitch, revolutions (9 mm outer radius), spacing along it
PAPER_REVOLUTIONS = 18.0
PAPER_SPACING_MM = 0.1


def archimedean_spiral(
    pitch_mm: float = PAPER_PITCH_MM, revolutions: float = PAPER_REVOLUTIONS, spacing_mm: float = PAPER_SPACING_MM
) -> np.ndarray:
    """Return (N, 2) points (mm) of r = pitch * theta / (2 pi), theta in [0, 2 pi revolutions].

    Points start at the centre and are equispaced `spacing_mm` along the curve (the
    last point is the end of the spiral). Paper defaults: pitch 0.5 mm, 18
    revolutions, 0.1 mm spacing: 5,090 points, 9 mm outer radius.
    """
    b = as_positive(pitch_mm, "pitch_mm")
    rev = as_positive(revolutions, "revolutions")
    ds = as_positive(spacing_mm, "spacing_mm")
    theta_end = 2.0 * np.pi * rev
    total = float(_arc_length(np.array(theta_end), b))
    s = np.append(np.arange(0.0, total, ds), total)
    # Invert s(theta) on a dense table; the table is fine enough for sub-um accuracy,
    # then one Newton step per point polishes it (ds/dtheta = a sqrt(1 + theta^2)).
    grid = np.linspace(0.0, theta_end, 200_001)
    theta = np.interp(s, _arc_length(grid, b), grid)
    a = b / (2.0 * np.pi)
    for _ in range(2):
        theta -= (_arc_length(theta, b) - s) / (a * np.sqrt(1.0 + theta**2))
    theta = np.clip(theta, 0.0, theta_end)
    r = a * theta
    return np.column_stack([r * np.cos(theta), r * np.sin(theta)])
