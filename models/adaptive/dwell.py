"""A beam held on one spot: the points the eye model takes from it.

Every fit of the adaptive model counts each A-scan as an independent point, so a beam
held still on one spot (the instrument resting while the OCT streams at 2 kHz) would
outweigh the scan: on a staphyloma whose model-building spiral ends on the pouch's wall,
34 s there (68,000 A-scans) moved the robust globe under the local model from 12.29 x
12.04 x 11.97 mm (MAE 117 um over the paper's reference region) to 12.92 x 11.51 x 10.87
mm (639 um), and the model the filter uses from MAE 28 to 533 um (README, Results). The
repeated A-scans measure nothing new but their noise.

The rule: of the finite points that follow one another within DWELL_RADIUS_MM of the
first of them (the anchor), the model takes the first DWELL_MAX_POINTS; a point farther
from the anchor becomes the next anchor. A scan moving at 4 mm/s or faster (2 um or more
between A-scans at 2 kHz) never reaches the cap: the closed loop's 15 mm/s spiral, the
planner's 5 mm/s sweeps and the paper's 0.1 mm spacing are taken whole. Non-finite
points are passed on (the update counts and rejects them). A floater farther than the
radius from the anchor restarts the count. Units: mm.
"""
from __future__ import annotations

import numpy as np
from numba import njit

DWELL_RADIUS_MM = 0.2  # a stretch of retina the noise of one A-scan (~20 um) cannot span
DWELL_MAX_POINTS = 100  # A-scans per stretch: a 4 mm/s scan's at 2 kHz

STATE_SIZE = 4  # [anchor (3,) mm (NaN: none yet), points taken within the radius of it]


def new_state() -> np.ndarray:
    """The rule's state before any point: no anchor."""
    return np.array([np.nan, np.nan, np.nan, 0.0])


@njit(cache=True)
def dwell_keep(P, state, radius_mm, max_points, keep):
    """keep[i] (bool, (M,)) = whether the model takes the point P[i] (P (M, 3) mm), by the
    module's rule, updating `state` (STATE_SIZE,) in place; returns how many it takes."""
    r2 = radius_mm * radius_mm
    n = 0
    for i in range(P.shape[0]):
        x, y, z = P[i, 0], P[i, 1], P[i, 2]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            keep[i] = True
            n += 1
            continue
        d0, d1, d2 = x - state[0], y - state[1], z - state[2]
        if not d0 * d0 + d1 * d1 + d2 * d2 <= r2:  # the first point, or one beyond the anchor's radius
            state[0], state[1], state[2], state[3] = x, y, z, 0.0
        keep[i] = state[3] < max_points
        if keep[i]:
            state[3] += 1.0
            n += 1
    return n


__all__ = ["DWELL_MAX_POINTS", "DWELL_RADIUS_MM", "STATE_SIZE", "dwell_keep", "new_state"]
