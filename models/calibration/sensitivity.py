"""The paper's Fig. 3 study: how an error in the sensor pose changes the fitted eye size.

A spherical "eye" (default radius 12 mm) is scanned as in the paper's simulation
(`models.scan.paper_scan`): trocar/RCM at (0, 0, 8) mm, the tip on the Archimedean
spiral in the plane z = 0, the beam along the trocar -> tip line, the distance the
exact ray/sphere intersection (plus optional noise). The points are then
reconstructed with a sensor pose that differs from the true one:
- vertically: the sensor origin assumed `offset` mm further along the beam (the
  instrument shaft axis), so every point moves by `offset` along its beam;
- rotated: the beam assumed tilted by `tilt` about an axis across the shaft (at
  an azimuth in the instrument's x-y plane), so every point swings sideways by
  about distance x tilt.
A sphere is fitted to the reconstructed points and its diameter compared with the
truth. The paper shows qualitatively that the diameter error grows with both
perturbations. Here the offset acts to first order (the beams meet the retina
nearly along its normal, so the radius follows the offset almost one for one),
while a tilt mostly shifts the cloud sideways and changes the diameter only
through the spread of distances (about 4-12 mm) across the spiral: a few um at
2 deg, with a sign and size that depend on the tilt's azimuth.

The instrument frame along the scan: z along the beam, and the frame carried from
the central pose (beam along -z of E, x along +x of E) by the smallest rotation
onto each beam, i.e. the instrument does not roll about its shaft while it pivots
about the RCM.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.eyes.eye import Eye
from models.eyes.pose import EyePose
from models.scan.paper_scan import Scan, paper_scan
from models.shapes.sphere import fit_sphere

SPHERE_RADIUS_MM = 12.0


def sphere_eye(radius_mm: float = SPHERE_RADIUS_MM) -> Eye:
    """A spherical ground-truth retina of `radius_mm` centred on the E (= W) origin."""
    if not np.isfinite(radius_mm) or radius_mm <= 8.0:
        raise ValueError(f"radius_mm must be finite and > 8 mm (the trocar sits at z = 8 mm), got {radius_mm!r}")
    return Eye("sphere", np.full(3, float(radius_mm)), EyePose())


def instrument_x_axes(beam_W: np.ndarray) -> np.ndarray:
    """(N, 3) instrument x axes in W for unit beams (N, 3): +x of W carried by the
    smallest rotation taking -z of W onto each beam (undefined for a beam along +z)."""
    c = np.array([0.0, 0.0, -1.0])
    v = np.cross(c, beam_W)
    k = 1.0 + beam_W @ c
    if np.any(k < 1e-9):
        raise ValueError("a beam points along +z: the instrument frame is undefined")
    e = np.array([1.0, 0.0, 0.0])
    ve = np.cross(v, e)
    return e + ve + np.cross(v, ve) / k[:, None]


def reconstructed_points(scan: Scan, offset_mm: float = 0.0, tilt_rad: float = 0.0, azimuth_rad: float = 0.0) -> np.ndarray:
    """(N, 3) retinal points in W (mm) rebuilt from `scan`'s distances with a sensor
    whose origin is `offset_mm` further along the beam and whose beam is tilted by
    `tilt_rad` about the instrument axis cos(azimuth) x + sin(azimuth) y."""
    b = scan.beam_W
    x = instrument_x_axes(b)
    axis = np.cos(azimuth_rad) * x + np.sin(azimuth_rad) * np.cross(b, x)
    tilted = np.cos(tilt_rad) * b + np.sin(tilt_rad) * np.cross(axis, b)
    return scan.p_WT + offset_mm * b + scan.distance_mm[:, None] * tilted


def diameter_error_um(scan: Scan, true_radius_mm: float, offset_mm: float = 0.0, tilt_rad: float = 0.0, azimuth_rad: float = 0.0) -> float:
    """Fitted minus true sphere diameter (um) for points rebuilt with the perturbed sensor."""
    fitted = fit_sphere(reconstructed_points(scan, offset_mm, tilt_rad, azimuth_rad))
    return float(2e3 * (fitted.radius - true_radius_mm))


@dataclass(frozen=True)
class SensitivityCurves:
    """Diameter errors (um): against the vertical offsets (um), shape (n_offsets,); and
    against the tilts (deg) for each tilt azimuth (deg), shape (n_azimuths, n_tilts)."""

    offsets_um: np.ndarray
    offset_diameter_error_um: np.ndarray
    tilts_deg: np.ndarray
    azimuths_deg: np.ndarray
    tilt_diameter_error_um: np.ndarray


def diameter_sensitivity(
    offsets_um,
    tilts_deg,
    azimuths_deg=(0.0, 90.0, 180.0, 270.0),
    radius_mm: float = SPHERE_RADIUS_MM,
    noise_um: float = 0.0,
    seed: int = 0,
    spacing_mm: float = 0.1,
) -> SensitivityCurves:
    """Sphere-diameter error for each vertical offset (um) and each tilt (deg) about
    each azimuth (deg, 0 = instrument x axis) of the sensor, from one spiral scan of
    a sphere of `radius_mm` with N(0, noise_um) distance noise."""
    offsets = np.asarray(offsets_um, dtype=float).ravel()
    tilts = np.asarray(tilts_deg, dtype=float).ravel()
    azimuths = np.asarray(azimuths_deg, dtype=float).ravel()
    for name, v in (("offsets_um", offsets), ("tilts_deg", tilts), ("azimuths_deg", azimuths)):
        if v.size == 0 or not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be a non-empty array of finite values")
    scan = paper_scan(sphere_eye(radius_mm), noise_um=noise_um, seed=seed, spacing_mm=spacing_mm)
    return SensitivityCurves(
        offsets,
        np.array([diameter_error_um(scan, radius_mm, offset_mm=o * 1e-3) for o in offsets]),
        tilts,
        azimuths,
        np.array([[diameter_error_um(scan, radius_mm, tilt_rad=np.radians(t), azimuth_rad=np.radians(az)) for t in tilts] for az in azimuths]),
    )
