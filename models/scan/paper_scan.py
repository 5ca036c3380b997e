"""The paper's simulated scan: the tip follows the spiral, the beam runs trocar -> tip.

`paper` scenario (design.md): RCM/trocar at (0, 0, 8) mm, the tip on the Archimedean
spiral in the coronal plane z = 0 centred on the visual axis, the beam along the
trocar -> tip line; each distance is the exact ray cast to the ground-truth retina
plus N(0, noise) noise. The scan is laid out in the *nominal* eye frame, which is W
here: an eye placed with a tilt or decentration (EyePose) is scanned off its own
axes, as a real eye would be.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.eyes.eye import Eye
from models.scan.spiral import archimedean_spiral


@dataclass(frozen=True, eq=False)
class Scan:
    """One simulated spiral scan in W: tip positions p_WT (N, 3) mm, unit beam
    directions (N, 3), true and measured distances (N,) mm, measured points (N, 3) mm."""

    p_WT: np.ndarray
    beam_W: np.ndarray
    true_distance_mm: np.ndarray
    distance_mm: np.ndarray

    @property
    def points(self) -> np.ndarray:
        """Measured retinal points (N, 3) in W: tip + measured distance along the beam."""
        return self.p_WT + self.distance_mm[:, None] * self.beam_W

    def __len__(self) -> int:
        return len(self.distance_mm)


def paper_scan(
    eye: Eye,
    noise_um: float = 20.0,
    seed: int = 0,
    p_WC=(0.0, 0.0, 8.0),
    plane_z_mm: float = 0.0,
    spacing_mm: float = 0.1,
) -> Scan:
    """Simulate the paper's spiral scan of `eye`: trocar at p_WC, spiral in the plane
    z = plane_z_mm of W (the nominal eye frame), centred on the z axis.

    `noise_um` >= 0 is the SD of the Gaussian distance noise; `seed` fixes it.
    `spacing_mm` is the spacing of the tip along the spiral (0.1 mm: 5,093 A-scans).
    """
    if not np.isfinite(noise_um) or noise_um < 0:
        raise ValueError(f"noise_um must be finite and >= 0, got {noise_um}")
    spiral = archimedean_spiral(spacing_mm=spacing_mm)
    p_WT = np.column_stack([spiral, np.full(len(spiral), plane_z_mm)])
    beam_W = p_WT - np.asarray(p_WC, dtype=float)
    beam_W /= np.linalg.norm(beam_W, axis=1, keepdims=True)
    true_d = eye.ray_cast(p_WT, beam_W)
    if not np.all(np.isfinite(true_d)):
        raise ValueError("some beams miss the retina: check the trocar and spiral placement")
    rng = np.random.default_rng(seed)
    measured = true_d + rng.normal(0.0, noise_um * 1e-3, len(true_d))
    return Scan(p_WT, beam_W, true_d, measured)
