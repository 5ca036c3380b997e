"""Compiled kernel of the innovation gate (models.adaptive.outlier_gate): which points of an
A-scan or packet to keep, with the gate's state in arrays updated in place."""
from __future__ import annotations

import numpy as np
from numba import njit

from models.fit.quadric_residuals import sampson_one

RESIDUAL_REFRESH = 16  # accepted points between refreshes of the gate's robust residual and jump limit (medians)
# models.adaptive.outlier_gate.GateState's state, in arrays the gate kernel updates in place:
# GATE_PARAMS indexes its float parameters, GATE_COUNTS its integer counters
G_K_RESIDUAL, G_MIN_GATE_MM, G_MIN_POINTS, G_MAX_CONSECUTIVE, G_MAX_JUMP_MM = range(5)
G_REFERENCE, G_RUN, G_N_RECENT, G_REFRESH_AT, G_N_REJECTED = range(5)
# counts[G_REFERENCE]: what the gate's `last` holds: nothing yet, the first point (not yet
# kept: pending until the next one confirms it), or the last point kept
REF_NONE, REF_PENDING, REF_KEPT = range(3)


@njit(cache=True)
def _model_distance(quadric, has_quadric, p0, scale, px, py, pz):
    """Sampson distance (mm) of the point (px, py, pz) mm from the quadric about p0 (0 without one)."""
    if not has_quadric:
        return 0.0
    return scale * sampson_one(quadric, (px - p0[0]) / scale, (py - p0[1]) / scale, (pz - p0[2]) / scale)


@njit(cache=True)
def _remember(counts, last, recent, px, py, pz, d, step):
    """Record a kept point (px, py, pz) mm at distance d mm from the model, `step` mm from
    the point kept before it, as the gate's reference."""
    last[0], last[1], last[2] = px, py, pz
    k = counts[G_N_RECENT] % recent.shape[1]
    recent[0, k], recent[1, k] = d, step
    counts[G_N_RECENT] += 1


@njit(cache=True)
def _refresh_scales(params, counts, scales, recent):
    """The robust residual (1.4826 x the median distance to the model, mm; inf before any
    point) and the jump limit (k_residual x the median step between consecutive kept
    points, within [min_gate_mm, max_jump_mm]; max_jump_mm before any point) of the last
    kept points `recent`, into scales (2,)."""
    m = min(counts[G_N_RECENT], recent.shape[1])
    if m == 0:
        scales[0], scales[1] = np.inf, params[G_MAX_JUMP_MM]
        return
    scales[0] = 1.4826 * np.median(recent[0, :m])
    scales[1] = min(params[G_MAX_JUMP_MM], max(params[G_MIN_GATE_MM], params[G_K_RESIDUAL] * np.median(recent[1, :m])))


@njit(cache=True)
def gate_points(P, keep, quadric, has_quadric, p0, scale, n_model_points, params, counts, last, scales, recent):
    """The innovation gate (models.adaptive.outlier_gate.OutlierGate) over the points P (N, 3) mm in
    A-scan order; sets keep[:N] and returns (the count of P's rows kept, whether the
    pending first point (in `last` at the call) was confirmed and is kept too, before
    P's rows), updating the gate's state in place: `counts` (GATE_COUNTS: int64), `last`
    (3,) the reference point (mm, see REF_*), `scales` (2,) the robust residual and the
    jump limit (mm, refreshed every RESIDUAL_REFRESH accepted points by _refresh_scales
    from `recent` (2, window): the distances to the model and the steps of the last
    accepted points, mm).
    `quadric` (10,) is the current model about p0 in coordinates (x - p0) / scale
    (ignored unless `has_quadric`: every distance is then 0). The very first point has
    nothing to be compared with: it is held as pending and kept only if the next point
    lies within the jump limit of it (else it is rejected and the next point is pending
    in its place), so that a floater on the first A-scan never becomes the reference
    that turns the retina away. Each later point's jump is measured from the last point
    kept before it, so a rejected floater never becomes the reference for the next
    A-scan; while more than max_consecutive far points have come in a row, they are
    kept: that is retina, not a floater."""
    if counts[G_N_RECENT] >= counts[G_REFRESH_AT]:  # the medians are refreshed every REFRESH points, not per point
        _refresh_scales(params, counts, scales, recent)
        counts[G_REFRESH_AT] = counts[G_N_RECENT] + RESIDUAL_REFRESH
    use_model = n_model_points >= params[G_MIN_POINTS] and scales[0] < np.inf
    gate = max(params[G_MIN_GATE_MM], params[G_K_RESIDUAL] * scales[0]) if use_model else np.inf
    max_jump = scales[1]
    n_kept = 0
    took_pending = False
    pending_at = -1  # the row of P held as pending, -1: the pending point came with an earlier call
    for n in range(P.shape[0]):
        px, py, pz = P[n, 0], P[n, 1], P[n, 2]
        jump = np.sqrt((px - last[0]) ** 2 + (py - last[1]) ** 2 + (pz - last[2]) ** 2)
        d = _model_distance(quadric, has_quadric, p0, scale, px, py, pz)
        if counts[G_REFERENCE] != REF_KEPT:  # no point kept yet: only a confirmed pair gets in
            keep[n] = counts[G_REFERENCE] == REF_PENDING and jump <= max_jump
            if not keep[n]:
                counts[G_N_REJECTED] += counts[G_REFERENCE] == REF_PENDING  # the previous first point: unconfirmed
                last[0], last[1], last[2] = px, py, pz
                counts[G_REFERENCE] = REF_PENDING
                pending_at = n
                continue
            _remember(counts, last, recent, last[0], last[1], last[2],
                      _model_distance(quadric, has_quadric, p0, scale, last[0], last[1], last[2]), jump)
            if pending_at >= 0:
                keep[pending_at] = True
                n_kept += 1
            else:
                took_pending = True
            counts[G_REFERENCE] = REF_KEPT
        else:
            near = jump <= max_jump and d <= gate
            counts[G_RUN] = 0 if near else counts[G_RUN] + 1
            keep[n] = near or counts[G_RUN] > params[G_MAX_CONSECUTIVE]  # a long run of far points is retina
            if not keep[n]:
                counts[G_N_REJECTED] += 1
                continue
        _remember(counts, last, recent, px, py, pz, d, jump)
        n_kept += 1
    return n_kept, took_pending

