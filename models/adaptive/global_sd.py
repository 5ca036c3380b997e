"""How far the ellipsoid under the local model may be off far from the data.

The local model reads the global quadric where no data came (models.local.grid), with that
quadric's standard deviation there: 0.3 mm for an eye's ellipsoid, the value the regular
eyes' ellipsoids meet once the scan has determined them. Two things make an ellipsoid worse
than that while the scan is young or a pathology pulls it, and the sd here covers both:

- its leverage (GLOBE_SD_FACTOR x extrapolation_sd of the robust globe's fit): how little
  of the globe the points see;
- its bias, which the leverage does not see: half the largest gap over the retina between
  it and a rival the data do not yet rule out (GAP_SD_SHARE). The rivals: the sphere,
  while its prediction loss on the new A-scans (models.fit.streaming_robust) is within
  CREDIBLE_LOSS_RATIO x the robust globe's over both memories; and, under the least-squares
  ellipsoid, the robust globe (both fitted to the same points: where they part, one is
  pulled by what the other leaves out).

Measured (the loop's spiral replayed into the model, seed 0, and the paper's spiral, seed 0;
3-sigma coverage of the local field over 60 x 60 reference samples at 40 and 60 points of
the scan; a script, not a test): without the gaps a least-squares ellipsoid taken at 12-25 %
of the loop's spiral kept the ellipsoid's 0.3 mm far sd while up to 2.6 mm off (detached eye,
10.2 x 10.1 x 8.2 mm): coverage 0.58 / 0.68 / 0.65 / 0.39 / 0.39 (emmetropic, myopic,
hyperopic, detached, staphyloma); on the paper's spiral the staphyloma's robust globe, taken
at 64 % and drawn out towards the pouch (15.3 x 13.0 x 12.6 mm), lay 2.7 mm beyond the
retina in front of the equator with a leverage sd of 0.65 mm: 5.3 % of the samples beyond
3 sigma on the unsafe side, by up to 0.71 mm. With them: 1.000 / 0.980 / 1.000 / 0.70 /
0.78, and no unsafe-side miss on the paper's staphyloma (with a loss ratio of 2: 2.4 %, up
to 0.23 mm); at the end of every build the sd is the ellipsoid's as before (the sphere's
loss is 2.7-68 x the globe's there, its held loss 8-29 x).
"""
from __future__ import annotations

import numpy as np

from models.adaptive.extrapolation import extrapolation_sd, largest_gaps
from models.eyes.eye import ANTERIOR_CROP_MM
from models.fit.ellipsoid_fit import LENGTH_SCALE_MM

# The robust globe's standard deviation far from the data: GLOBE_SD_FACTOR x the largest over
# the retina of its fit's own, were its residuals independent (extrapolation_sd: the leverage of
# a globe seen over a small part of the retina). They are not: 500 stored points subsample a
# scan whose errors are correlated over millimetres, and a pathology's flank down-weighted but
# not left out biases the fit. Measured in 12 faults-campaign builds (seed 0; the accel_limit
# class on every shape but the hyperopic eye, the detached eye's and the staphyloma's
# time_offset, the detached eye's floaters, and three builds of a choice then being tried): 40
# deg and more from the data, a globe's error p99 was 0.9-7.0 x that sd at the same point where
# the globe was within 0.41 mm of the eye's retina (where that sd is 20-170 um the ellipsoid's
# 0.3 mm covers; the pointed eye's globe, no eye's, is never taken), and 7.1-8.2 x on a detached
# eye's globe of 13.08 x 12.54 x 12.36 mm fitted to a quarter of the reference region (the eye
# 12.30 x 11.97 x 11.95; 1.76 mm off, p99, 1.86 max). The largest sd over the retina, which the
# rule takes, was 0.26 mm there (6.8 x less than that p99) and 0.14 mm on the same class's good
# globe. 3 makes the barrier's 3 sd 9 x it (2.3 mm there); the local model takes it where no
# data came within 30 deg (models.local.grid.LocalRetinaModel.update's shape_sd_mm) and never
# below the ellipsoid's (models.local.config.LocalConfig.ellipsoid_sd_far_mm).
GLOBE_SD_FACTOR = 3.0
GAP_SD_SHARE = 0.5  # 3 sd = 1.5 x the gap: the bound covers the rival's surface and half as much again
CREDIBLE_LOSS_RATIO = 3.0  # the sphere is a rival while its loss is below 3 x the globe's (both memories)


class GlobalSd:
    """The sd far from the data (mm) of the ellipsoid under the local model, from the
    measures of the robust globe's last fit (once per fit; a caller adding one A-scan at a
    time spreads them over two updates): its leverage sd `leverage_mm` (GLOBE_SD_FACTOR x
    extrapolation_sd; inf before a fit; `measure_leverage`) and the largest gaps over the
    retina, mm, of the globe from the sphere (`globe_to_sphere_mm`) and of the least-squares
    ellipsoid from the sphere and from the globe (`ls_to_sphere_mm`, `ls_to_globe_mm`; 0
    without an eye's least-squares fit; `measure_gaps`, `gaps_due` until then)."""

    def __init__(self):
        self.fit = None  # the globe's fit measured
        self.leverage_mm = np.inf
        self.globe_to_sphere_mm = self.ls_to_sphere_mm = self.ls_to_globe_mm = 0.0
        self.gaps_due = False

    def measure_leverage(self, globe) -> None:
        """The leverage sd of the robust globe `globe`'s last fit (models.fit.streaming_robust)."""
        fit = self.fit = globe.last_ok
        self.leverage_mm = GLOBE_SD_FACTOR * extrapolation_sd(globe.last_scatter, fit.v, fit.center, fit.radii,
                                                              fit.rotation, globe.p0, LENGTH_SCALE_MM, ANTERIOR_CROP_MM)
        self.gaps_due = True

    def measure_gaps(self, globe, sphere, ls_fit, ls_S, ls_p0) -> None:
        """The gaps of the globe's fit measured (`fit`) from the Sphere `sphere` (or None)
        and of the least-squares EllipsoidFit `ls_fit` (None, or an eye's, fitted to the
        scatter matrix ls_S about ls_p0) from the sphere and the globe."""
        fit, self.gaps_due = self.fit, False
        self.globe_to_sphere_mm = 0.0 if sphere is None else largest_gaps(
            globe.last_scatter, fit.center, fit.radii, fit.rotation, globe.p0, LENGTH_SCALE_MM, ANTERIOR_CROP_MM, sphere)[0]
        if ls_fit is None or sphere is None:
            self.ls_to_sphere_mm = self.ls_to_globe_mm = 0.0
        else:
            self.ls_to_sphere_mm, self.ls_to_globe_mm = largest_gaps(
                ls_S, ls_fit.center, ls_fit.radii, ls_fit.rotation, ls_p0, LENGTH_SCALE_MM, ANTERIOR_CROP_MM, sphere,
                fit.v, globe.p0)

    @staticmethod
    def sphere_credible(globe) -> bool:
        """Whether the sphere is still a rival: its prediction loss within CREDIBLE_LOSS_RATIO x
        the robust globe's over both memories (or no losses yet to say otherwise)."""
        short, held = globe.rival_loss_mm2 / globe.loss_mm2, globe.held_rival_loss_mm2 / globe.held_loss_mm2
        return not (short >= CREDIBLE_LOSS_RATIO or held >= CREDIBLE_LOSS_RATIO)  # NaN: no evidence against it

    def of_globe(self, globe) -> float:
        """The robust globe's sd far from the data, mm."""
        gap = self.globe_to_sphere_mm if self.sphere_credible(globe) else 0.0
        return max(self.leverage_mm, GAP_SD_SHARE * gap)

    def of_least_squares(self, globe) -> float | None:
        """The least-squares ellipsoid's sd far from the data, mm (None before the globe's
        first fit: the ellipsoid's own)."""
        if self.fit is None:
            return None
        gap = max(self.ls_to_globe_mm, self.ls_to_sphere_mm if self.sphere_credible(globe) else 0.0)
        return max(self.leverage_mm, GAP_SD_SHARE * gap)
