"""The local retina model's settings (models.local.grid: what each does and why its value).
Units: deg, mm, mm/rad, mm/rad^2 as named.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LocalConfig:
    """The local model's grid and priors (deg, mm, mm/rad, mm/rad^2).

    The global model's standard deviation, next to the data and far from it: on a sphere
    `sd_near_mm` 0.15, `sd_far_mm` 2.0 (a sphere fitted to a posterior cap is off by
    1.3-1.6 mm at the equator of the oblate emmetropic globe, 11.46/10.15 mm semi-axes, and
    by up to 4.9 mm within the paper's reference region on the pointed eye, whose cap's
    sphere in the loop has a radius of 9.5-9.7 mm: 3 x 2.0 covers it; next to the data,
    the largest RMS residual of a sphere over a detachment, 0.1-0.15 mm); on an ellipsoid (one whose semi-axes are an eye's)
    `ellipsoid_sd_near_mm` 0.05 and `ellipsoid_sd_far_mm` 0.3 (the ellipsoid's exact MAE
    over the whole retina on the regular eyes, 25-65 um in the loop, its worst extrapolated
    points a few times that; a robust globe seen over less of the retina may bring a larger
    one of its own: models.adaptive.global_sd). `sd_floor_mm` 0.02, added in quadrature to every sd: the
    model claims to know the retina no better than one A-scan measures it (20 um distance
    noise); the quadratics' bias between scan lines has terms of its own (above).
    `departure_floor_mm` 0.03: the least departure from the global quadric that counts (at
    0.02 mm the local plans of the detached eye and the staphyloma, seed 0, had the
    filter step in on 0.98 % and 0.97 % of the steps; at 0.03 mm on 0.36 % and 0.31 %).
    Measured on the loop's
    spiral (seed 0, the six shapes and the four variants of the issue's targets: 3 mm
    staphyloma, detachments 3.5 mm at 25 deg and 1 mm at 60 deg, pointed apex 4 mm): the
    exact error within 1 deg of the data is at most 1.7 sd, 3 sd covers every reference
    sample, and where the model's retina lies beyond the true one it does so by at least
    32 um less than 3 sd. The boundary next to the data is then d_safe + 0.06 mm (a 0.03 mm
    floor makes it 0.09 mm and keeps the pointed eye's cutter 0.652-0.655 mm from its retina).
    `departure_deg` 25: how far past the data a departure from the global quadric counts
    (about a detachment's or a staphyloma's radius: the default detachment, 10 mm across,
    spans 25 deg from its centre; with 15 deg the variant 3.5 mm high at 25 deg kept
    0.25 % of its reference samples beyond 3 sigma on the unsafe side, up to 0.59 mm).
    `sample_length_mm` 0.2: the A-scans of one stretch of scan line this long on the
    retina count as one sample (each weighs its lateral step from the previous one over
    this length, at most 1, measured across its beam when the update is given the beams'
    directions: the distance noise lies along the beam; models.local.kernels.absorb_points). At 2 kHz the loop's
    A-scans lie 8-15 um apart on the retina, and their errors are not independent: 55 % of
    the extractor's error variance is common to A-scans more than 5 mm apart along the
    loop's spiral (seed 0, every shape). Counted one by one they held each node's quadratic
    to its few scan lines against the prior, and the quadratics bent between the lines:
    the paper's spiral pitch through the loop (18 revolutions, 10 mm/s), replayed into the
    model, gave the staphyloma a scanned p95 of 85 um; at one sample per 0.1 / 0.2 / 0.3 /
    1.0 mm, 55 / 44 / 40 / 38 um (the detached eye 34 -> 30 / 29 / 29 / 30 um; on the
    default spiral the detached eye 348 -> 261 / 235 / 218 / 177 and the staphyloma
    484 -> 389 / 364 / 347 / 333 um, the regular eyes 36-44 -> 24-25 um, while the pointed
    eye's 531 um on the dense spiral rises to 593 / 631 / 664 / 719 um). 0.2 mm is the
    paper's own sampling on the retina (its spiral's points, 0.1 mm apart in the
    instrument's plane, lie 0.13-0.22 mm apart there): every point of its simulation still
    counts in full. `trend_deg` 15: how far past the data the nodes read the trend quadric
    (models.adaptive.model.AdaptiveEyeModel.quadrics_for_local: the ellipsoid the data
    support when its semi-axes are no eye's) instead of the global one, and the quadric the
    nodes' quadratics are centred on. The pointed eye's scan sees its posterior
    paraboloid, which its sphere misses by 0.9-1.7 mm at 2-10 deg past the data and its
    177 x 31 x 31 mm ellipsoid by 30-51 um (p95); that ellipsoid is 0.48 mm off at 10-15
    deg, 1.2 mm at 15-20 and 2.6 mm at 20-30 deg, beyond the retina (the sphere lies
    inside it), so it stops at 15 deg and the sd (the global quadric's, unchanged) covers
    it to there. Replayed loop points (seed 0, the paper's spiral pitch at 10 mm/s):
    scanned p95 631 um without the trend, 55 / 33 / 30 / 30 um with 10 / 12 / 15 / 20 deg,
    3-sigma coverage 1.000 and no unsafe-side miss in each.
    `support_deg` 12: the angle over which a node's quadratic weighs the points (Wendland).
    Where scan lines lie several degrees apart across a steep wall a narrower quadratic
    bends between them: measured on the loop's spiral (seed 0), the 3 mm staphyloma's
    scanned p95 was 192 / 165 / 111 / 64 / 38 um at 7.5 / 7 / 9 / 10.5 / 12 deg (its errors
    at 9 deg on the pouch's wall, 20-40 deg from its centre, 1-2 deg from the data; MAE 40 /
    41 / 37 / 36 / 35 um), the default staphyloma's 36 / 29 / 27 at 9 / 10.5 / 12 and the
    detachment 3.5 mm high at 25 deg 43 / 38 / 40 um; the regular and pointed eyes the same
    to 0.5 um. A point touches (12/9)^2 = 1.8 x as many nodes: +3 us per A-scan in packets.
    `solves_per_point` 4, `sweep_per_point` 0.2: per point given, up to 4 solves of the nodes
    it touched and 0.2 re-solves of the nodes with data in turn (the global prior moves): 4
    per packet of 20 A-scans, 1 per 5 single A-scans (a packet needs 43 solves on average,
    p90 55; 8 per point would be spent on every single A-scan, 2.2 per A-scan in packets)."""

    spacing_deg: float = 3.0
    support_deg: float = 12.0
    blend_deg: float = 4.8
    track_deg: float = 30.0
    noise_mm: float = 0.02
    sd_near_mm: float = 0.15
    sd_far_mm: float = 2.0
    ellipsoid_sd_near_mm: float = 0.05
    ellipsoid_sd_far_mm: float = 0.3
    far_deg: float = 30.0
    length_deg: float = 10.0
    sd_floor_mm: float = 0.02
    min_radius_mm: float = 6.0
    max_radius_mm: float = 20.0
    gate_mm: float = 5.0
    fitted_terms: int = 6
    refresh: int = 5
    solves_per_point: int = 4
    sweep_per_point: float = 0.2
    relist_growth: float = 0.05
    departure_deg: float = 25.0
    departure_floor_mm: float = 0.03
    sample_length_mm: float = 0.2
    trend_deg: float = 15.0

    def __post_init__(self):
        for name in ("spacing_deg", "support_deg", "blend_deg", "track_deg", "noise_mm", "sd_near_mm", "sd_far_mm",
                     "far_deg", "length_deg", "sd_floor_mm", "ellipsoid_sd_near_mm", "ellipsoid_sd_far_mm", "departure_deg",
                     "departure_floor_mm", "sample_length_mm", "trend_deg"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"LocalConfig.{name} must be finite and > 0, got {v}")
        if not 0.5 <= self.spacing_deg <= 20.0:
            raise ValueError(f"LocalConfig.spacing_deg must be in [0.5, 20] deg, got {self.spacing_deg}")
        if self.support_deg < 1.5 * self.spacing_deg or self.blend_deg < self.spacing_deg:
            raise ValueError("LocalConfig: support_deg must be >= 1.5 x spacing_deg and blend_deg >= spacing_deg")
        if self.departure_deg < self.blend_deg:  # a departing node's table (departure_deg) holds its blend neighbours too
            raise ValueError(f"LocalConfig: departure_deg ({self.departure_deg}) must be >= blend_deg ({self.blend_deg})")
        for name, least in (("solves_per_point", 0), ("refresh", 1)):  # the compiled step trusts them (no bounds checks)
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and v >= least):
                raise ValueError(f"LocalConfig.{name} must be an integer >= {least}, got {v!r}")
        if self.fitted_terms not in (1, 3, 6) or not (np.isfinite(self.sweep_per_point) and self.sweep_per_point >= 0.0):
            raise ValueError(f"LocalConfig: fitted_terms must be 1, 3 or 6 and sweep_per_point finite and >= 0, got "
                             f"{self.fitted_terms!r}, {self.sweep_per_point!r}")
        if self.sd_far_mm < self.sd_near_mm:
            raise ValueError(f"LocalConfig.sd_far_mm ({self.sd_far_mm}) must be >= sd_near_mm ({self.sd_near_mm})")

    def prior_for(self, ellipsoid: bool) -> np.ndarray:
        """The kernels' prior vector [noise, sd near, sd far, far rad, length rad, sd floor,
        fitted terms, departure floor] on a global sphere or, with `ellipsoid`, a global ellipsoid."""
        near, far = (self.ellipsoid_sd_near_mm, self.ellipsoid_sd_far_mm) if ellipsoid else (self.sd_near_mm, self.sd_far_mm)
        return np.array([self.noise_mm, near, far, np.radians(self.far_deg), np.radians(self.length_deg),
                         self.sd_floor_mm, self.fitted_terms, self.departure_floor_mm])
