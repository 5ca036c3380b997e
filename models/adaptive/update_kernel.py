"""The adaptive model's update (models.adaptive.model) as one compiled call: gate, sphere
filter, scatter matrix, scan range, refit and residuals, by one A-scan or a packet."""
from __future__ import annotations

import numpy as np
from numba import njit

from models.adaptive.gate_kernels import gate_points
from models.adaptive.scan_range_kernels import diameter_after_adding
from models.fit.quadric_kernels import add_design_rows, fit_ellipsoid_scatter, spread_check_due
from models.fit.quadric_residuals import taubin_residuals
from models.fit.sphere_kernels import sphere_absorb, sphere_center_radius


@njit(cache=True)
def fit_summary(S, sf_state, sf_ok, v_ef, ef_ok, radii, prev_radii, has_prev, v_sf, scale):
    """(sphere residual mm, ellipsoid residual mm, axis change) of one update of the
    adaptive model: the RMS distances (Taubin, taubin_residuals) over the points of S of
    the sphere (state [c, r^2 - |c|^2] in the fits' coordinates scaled by `scale` mm; its
    quadric is written to v_sf (10,)) and of the ellipsoid v_ef (NaN for a fit that is
    not ok), and the largest relative change of the sorted semi-axes `radii` since
    `prev_radii` (NaN unless `has_prev` and ef_ok); prev_radii then holds the sorted
    radii (the caller keeps has_prev = ef_ok)."""
    V = np.empty((2, 10))
    k = 0
    if sf_ok:
        cx, cy, cz, c = sf_state[0], sf_state[1], sf_state[2], sf_state[3]
        v_sf[0], v_sf[1], v_sf[2], v_sf[3], v_sf[4], v_sf[5] = 1.0, 1.0, 1.0, 0.0, 0.0, 0.0
        v_sf[6], v_sf[7], v_sf[8], v_sf[9] = -cx, -cy, -cz, -c
        V[k] = v_sf
        k += 1
    if ef_ok:
        V[k] = v_ef
        k += 1
    res = scale * taubin_residuals(S, V[:k])
    sf_res = res[0] if sf_ok else np.nan
    ef_res = res[k - 1] if ef_ok else np.nan
    axis_change = np.nan
    if ef_ok:
        r = np.sort(radii)
        if has_prev:
            axis_change = 0.0
            for i in range(3):
                axis_change = max(axis_change, abs(r[i] - prev_radii[i]) / prev_radii[i])
        prev_radii[:] = r
    return sf_res, ef_res, axis_change


# the layout of packet_update's output vector `out`
OUT_STATE, OUT_V_SF, OUT_V_EF, OUT_CENTER, OUT_RADII, OUT_ROTATION, OUT_SF_CENTER, OUT_SIZE = 0, 4, 14, 24, 27, 30, 39, 42


@njit(cache=True)
def packet_update(P, n, p0, gate_on, quadric, has_quadric, g_params, g_counts, g_last, g_scales, g_recent,
                  Y, y, refit, S, checked_at, recheck, X, block_r, diameter, prev_radii, has_prev, scale, kept, rows,
                  out):
    """The adaptive model's update by the points P (N, 3) mm (one A-scan's or a packet's), in
    one call. A model of n points, p0 (mm) the origin of every part (its first point; when
    n = 0 the first point kept here is written to p0), skips the non-finite rows of P,
    gates the others (gate_points, when `gate_on`; `quadric` the current model about p0)
    and copies those it keeps to kept[:K] (kept: (N + 1, 3): the gate may add its pending
    first point) and their rows of P to rows[:K] (rows (N + 1,) int: the pending point, an
    A-scan of an earlier call, takes the row of the point that confirms it, its neighbour
    in the stream); if K > 0 it absorbs them into the sphere filter (Y, y) and the scan range
    (X with room for K more rows, block_r, `diameter` mm) and, when `refit`, into the
    scatter matrix S, refits the ellipsoid (with the spread test when
    spread_check_due(checked_at, n + K, recheck)) and summarises the fits (fit_summary),
    all state updated in place. Without `refit` the caller fits the ellipsoid to kept[:K]
    itself (the robust fit, models.fit.robust_fit, reweights its points).

    Returns (non-finite count, K, spread test run, sphere ok, fit status code, diameter mm,
    sphere residual mm, ellipsoid residual mm, axis change, sphere radius mm); with K > 0,
    `out` (OUT_SIZE,) receives the sphere state and centre (mm) and, when `refit`, the
    sphere's quadric and the fit's quadric, centre, semi-axes and rotation (row-major).
    The fit's values are 0 (status, spread test) or NaN (residuals, axis change) without
    `refit`.
    """
    m = 0
    for i in range(P.shape[0]):  # row 0 is left for the gate's pending first point
        if np.isfinite(P[i, 0]) and np.isfinite(P[i, 1]) and np.isfinite(P[i, 2]):
            kept[m + 1, 0], kept[m + 1, 1], kept[m + 1, 2] = P[i, 0], P[i, 1], P[i, 2]
            rows[m + 1] = i
            m += 1
    n_nonfinite, k = P.shape[0] - m, 0
    keep = np.ones(m, np.bool_)
    took_pending = False
    if gate_on and m > 0:
        pending_x, pending_y, pending_z = g_last[0], g_last[1], g_last[2]
        if gate_points(kept[1:m + 1], keep, quadric, has_quadric, p0, scale, n, g_params, g_counts, g_last,
                       g_scales, g_recent)[1]:
            kept[0, 0], kept[0, 1], kept[0, 2] = pending_x, pending_y, pending_z
            k, took_pending = 1, True
    for i in range(m):
        if keep[i]:
            kept[k, 0], kept[k, 1], kept[k, 2] = kept[i + 1, 0], kept[i + 1, 1], kept[i + 1, 2]
            rows[k] = rows[i + 1]
            k += 1
    if took_pending:
        rows[0] = rows[1] if k > 1 else 0
    if k == 0:
        return n_nonfinite, 0, False, False, 0, diameter, np.nan, np.nan, np.nan, np.nan
    A = kept[:k]
    if n == 0:
        p0[0], p0[1], p0[2] = A[0, 0], A[0, 1], A[0, 2]
    state, sf_ok = sphere_absorb(Y, y, A, p0, scale, n + k)
    diameter = diameter_after_adding(X, block_r, n, A, p0, diameter)
    out[OUT_STATE:OUT_V_SF] = state
    radius = sphere_center_radius(state, p0, scale, out[OUT_SF_CENTER:OUT_SIZE]) if sf_ok else np.nan
    if not refit:
        return n_nonfinite, k, False, sf_ok, 0, diameter, np.nan, np.nan, np.nan, radius
    add_design_rows(S, A, p0, scale)
    check = spread_check_due(checked_at, n + k, recheck)
    code, v, center, radii, R = fit_ellipsoid_scatter(S, p0, scale, check)
    sf_res, ef_res, axis_change = fit_summary(S, state, sf_ok, v, code == 0, radii, prev_radii, has_prev,
                                              out[OUT_V_SF:OUT_V_EF], scale)
    out[OUT_V_EF:OUT_CENTER] = v
    out[OUT_CENTER:OUT_RADII] = center
    out[OUT_RADII:OUT_ROTATION] = radii
    out[OUT_ROTATION:OUT_SF_CENTER] = R.ravel()
    return n_nonfinite, k, check, sf_ok, code, diameter, sf_res, ef_res, axis_change, radius
