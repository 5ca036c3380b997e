"""Closest points on an ellipsoid and its exact signed distance (Eberly's construction, root
by safeguarded Newton): one compiled query for every point, and the closest points in NumPy.

Reference: D. Eberly, "Distance from a point to an ellipse, an ellipsoid, or a
hyperellipsoid". For semi-axes e0 >= e1 >= e2 and a query y in the first octant
the closest point is x_i = e_i^2 y_i / (t + e_i^2) where t is the unique root of
F(t) = sum (e_i y_i / (t + e_i^2))^2 - 1 on (-e_m^2, inf), e_m the smallest axis
whose coordinate is non-zero. Zero coordinates drop the problem to a lower
dimension, except on the plane of the smallest axis, where the closest point can
leave the plane (the query sits between the foci: the t = -e_m^2 branch).
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models.shapes.field import field_outputs

_MAX_STEPS = 200  # safeguarded Newton: quadratic near the root, never slower than bisection
_EPS = float(np.finfo(float).eps)


def _shifted_root(E2: np.ndarray, Y: np.ndarray, em2: np.ndarray) -> np.ndarray:
    """Root u = t + em2 of F(t) = sum_i (e_i y_i / (t + e_i^2))^2 - 1 on t in (-em2, inf), per row.

    E2: (3,) squared semi-axes; Y: (M, 3) non-negative, zero where a coordinate is
    inactive; em2: (M,) squared smallest active semi-axis. Solving for the shift u > 0
    instead of t keeps the smallest axis's denominator (exactly u) free of the
    cancellation t + em2 that ruins queries a hair off the plane of that axis.
    F is decreasing; Newton runs on phi(u) = (F + 1)^(-1/2) - 1, which has the same
    root and is almost linear (exactly so when one term dominates), inside the bracket
    [lo, hi] kept by the sign of F; a step that would leave the bracket is replaced by
    plain Newton on F (which stays inside from the left of the root, F being convex),
    else by bisection in log u (lo > 0). A row stops when the bracket or the step
    reaches rounding level. Compiled (numba): a row's iteration is a few scalar steps,
    for which NumPy's per-call overhead was most of a control step's distance query.
    """
    return _shifted_root_rows(np.ascontiguousarray(E2, dtype=float), np.ascontiguousarray(Y, dtype=float),
                              np.ascontiguousarray(em2, dtype=float))


@njit(cache=True)
def _shifted_root_rows(E2, Y, em2):
    M = Y.shape[0]
    out = np.empty(M)
    e = np.sqrt(E2)
    for m in range(M):
        out[m] = _shifted_root_row(E2[0], E2[1], E2[2], e[0], e[1], e[2], Y[m, 0], Y[m, 1], Y[m, 2], em2[m])
    return out


@njit(cache=True)
def _shifted_root_row(E20, E21, E22, e0, e1, e2, y0, y1, y2, em2):
    """One row of _shifted_root, in scalars: squared semi-axes E2i, semi-axes ei, the
    query yi, em2 its squared smallest active axis (no array allocated: at a few points
    per control step an allocation costs more than an iteration)."""
    rel_tol = 4.0 * _EPS
    e_bar2 = (E20 + E21 + E22) / 3.0
    ey0, ey1, ey2 = e0 * y0, e1 * y1, e2 * y2
    D0, D1, D2 = E20 - em2, E21 - em2, E22 - em2  # den_i = u + D_i, exactly u for the smallest axis
    em = np.sqrt(em2)
    y_m = 0.0
    if D0 == 0.0 and y0 > y_m:
        y_m = y0
    if D1 == 0.0 and y1 > y_m:
        y_m = y1
    if D2 == 0.0 and y2 > y_m:
        y_m = y2
    hi = 0.0 + ey0 + ey1 + ey2  # F(hi) <= 0 (>= |ey|, and no squares to underflow for tiny queries)
    norm2 = 0.0 + y0 * y0 + y1 * y1 + y2 * y2
    lo = em * y_m  # F(lo) >= 0: the smallest-axis term alone reaches 1
    # start: the root for a sphere of the mean radius (exact when the radii are equal),
    # kept inside the bracket; from either side of the root the next step lands left of it
    u = min(max(np.sqrt(e_bar2) * np.sqrt(norm2) - e_bar2 + em2, lo), hi)
    for _ in range(_MAX_STEPS):
        S = 0.0
        dS = 0.0
        if ey0 != 0.0:  # inactive terms (their denominator may vanish)
            den = u + D0
            r = ey0 / den
            S += r * r
            dS -= 2.0 * r * r / den
        if ey1 != 0.0:
            den = u + D1
            r = ey1 / den
            S += r * r
            dS -= 2.0 * r * r / den
        if ey2 != 0.0:
            den = u + D2
            r = ey2 / den
            S += r * r
            dS -= 2.0 * r * r / den
        F = S - 1.0
        if F > 0.0:
            lo = u
        else:
            hi = u
        # Newton on phi = S^(-1/2) - 1 (same root): nearly linear in u, since one term
        # dominates S near the pole, where Newton on F itself crawls
        root = np.sqrt(S)
        step = u + 2.0 * (1.0 / root - 1.0) * S * root / dS
        step_F = u - F / dS  # plain Newton on the convex F: inside the bracket from its left
        if lo < step < hi:
            new = step
        elif lo < step_F < hi:
            new = step_F
        else:  # geometric bisection: the root may sit many decades below hi
            new = np.sqrt(lo) * np.sqrt(hi)
        at_root = abs(F) <= 8.0 * _EPS * S  # F at rounding level: u is the root
        if at_root:
            new = u
        tol = rel_tol * new  # relative to the shift itself: no absolute floor to cancel against
        converged = at_root or abs(new - u) <= tol or hi - lo <= tol
        u = new
        if converged:
            break
    return u


@njit(cache=True)
def _planar_closest_point(E20, E21, E22, e0, e1, e2, y0, y1):
    """(x0, x1, x2): the closest point, in the first octant, on the ellipsoid with squared
    semi-axes E2i (E20 >= E21 >= E22) and semi-axes ei to the query (y0, y1, 0) >= 0 on the
    plane of its smallest axis (closest_point_first_octant's second branch, in scalars).
    Between the foci (the t = -e2^2 case) the closest point leaves the plane; elsewhere it
    is the 2-D ellipse's of semi-axes (e0, e1)."""
    d0, d1 = E20 - E22, E21 - E22
    if (y0 == 0.0 or d0 > 0.0) and (y1 == 0.0 or d1 > 0.0):
        xb0 = E20 * y0 / d0 if y0 > 0.0 else 0.0
        xb1 = E21 * y1 / d1 if y1 > 0.0 else 0.0
        disc = 1.0 - ((xb0 / e0) ** 2 + (xb1 / e1) ** 2)
        if disc > 0.0:
            return xb0, xb1, e2 * np.sqrt(disc)
    if y1 > 0.0:  # the ellipse's root with its smaller axis e1 (a third axis of 1 mm, inactive)
        u = _shifted_root_row(E20, E21, 1.0, np.sqrt(E20), np.sqrt(E21), 1.0, y0, y1, 0.0, E21)
        return E20 * y0 / (u + (E20 - E21)), E21 * y1 / (u + (E21 - E21)), 0.0
    d = E20 - E21  # on the longest axis: its end, or the point between the ellipse's foci
    x0 = E20 * y0 / d if d > 0.0 else np.inf
    if x0 < e0:
        return x0, e1 * np.sqrt(max(1.0 - (x0 / e0) ** 2, 0.0)), 0.0
    return e0, 0.0, 0.0


@njit(cache=True)
def ellipsoid_distance_and_gradient(center, rotation, radii, Q):
    """(d (M,) signed distance mm, > 0 inside; g (M, 3) unit inward normal at the closest
    point) of the points Q (M, 3) mm to the ellipsoid (center (3,) mm, rotation (3, 3) with
    the semi-axes' directions as columns, radii (3,) mm) in the points' frame, in one
    compiled pass for every point: off the plane of the smallest axis the generic case of
    Eberly's construction (zero coordinates of the other axes included), on it
    `_planar_closest_point`. At the centre the closest point is the + end of the smallest
    axis. Non-finite rows give NaN. Written in scalars (the axes sorted by a stable
    insertion sort, largest first: argsort(-radii) "mergesort"'s order), allocating only
    the outputs."""
    o0, o1, o2 = 0, 1, 2
    if radii[o1] > radii[o0]:
        o0, o1 = o1, o0
    if radii[o2] > radii[o1]:
        o1, o2 = o2, o1
        if radii[o1] > radii[o0]:
            o0, o1 = o1, o0
    e0, e1, e2 = radii[o0], radii[o1], radii[o2]
    E20, E21, E22 = e0 * e0, e1 * e1, e2 * e2
    d, g, finite = field_outputs(Q)
    for m in range(Q.shape[0]):
        if not finite[m]:
            continue
        q0, q1, q2 = Q[m, 0] - center[0], Q[m, 1] - center[1], Q[m, 2] - center[2]
        L0 = 0.0 + q0 * rotation[0, o0] + q1 * rotation[1, o0] + q2 * rotation[2, o0]  # coordinates on the sorted axes
        L1 = 0.0 + q0 * rotation[0, o1] + q1 * rotation[1, o1] + q2 * rotation[2, o1]
        L2 = 0.0 + q0 * rotation[0, o2] + q1 * rotation[1, o2] + q2 * rotation[2, o2]
        y0, y1, y2 = abs(L0), abs(L1), abs(L2)
        k = 0.0 + (L0 / e0) ** 2 + (L1 / e1) ** 2 + (L2 / e2) ** 2
        if y2 > 0.0:
            u = _shifted_root_row(E20, E21, E22, e0, e1, e2, y0, y1, y2, E22)
            x0 = E20 * y0 / (u + (E20 - E22))
            x1 = E21 * y1 / (u + (E21 - E22))
            x2 = E22 * y2 / (u + (E22 - E22))
        else:  # on the smallest axis's plane: the closest point may leave it
            x0, x1, x2 = _planar_closest_point(E20, E21, E22, e0, e1, e2, y0, y1)
        dist = np.sqrt(0.0 + (y0 - x0) ** 2 + (y1 - x1) ** 2 + (y2 - x2) ** 2)
        x0 = x0 if L0 >= 0.0 else -x0
        x1 = x1 if L1 >= 0.0 else -x1
        x2 = x2 if L2 >= 0.0 else -x2
        d[m] = dist if k < 1.0 else -dist
        # inward normal: -R (x / e^2) in the points' frame
        n0 = 0.0 - rotation[0, o0] * x0 / E20 - rotation[0, o1] * x1 / E21 - rotation[0, o2] * x2 / E22
        n1 = 0.0 - rotation[1, o0] * x0 / E20 - rotation[1, o1] * x1 / E21 - rotation[1, o2] * x2 / E22
        n2 = 0.0 - rotation[2, o0] * x0 / E20 - rotation[2, o1] * x1 / E21 - rotation[2, o2] * x2 / E22
        norm = np.sqrt(0.0 + n0 * n0 + n1 * n1 + n2 * n2)
        g[m, 0], g[m, 1], g[m, 2] = n0 / norm, n1 / norm, n2 / norm
    return d, g


def closest_point_first_octant(e: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Closest points X (M, 3) on the ellipsoid with semi-axes e (3,), e0 >= e1 >= e2 > 0,
    to queries Y (M, 3) with all coordinates >= 0."""
    E2 = e**2
    X = np.zeros_like(Y)
    pos = Y > 0.0

    # y2 > 0: generic root with the smallest axis e2 (inactive y0, y1 give x = 0).
    a = pos[:, 2]
    if a.any():
        u = _shifted_root(E2, Y[a], np.full(a.sum(), E2[2]))
        X[a] = E2 * Y[a] / (u[:, None] + (E2 - E2[2]))

    # y2 = 0: the t = -e2^2 branch leaves the plane when the query lies between the foci.
    b = ~a
    if b.any():
        Yb = Y[b]
        d = E2[:2] - E2[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xb = np.where(Yb[:, :2] > 0.0, E2[:2] * Yb[:, :2] / d, 0.0)
        inside = np.all((Yb[:, :2] == 0.0) | (d > 0.0), axis=1)
        disc = 1.0 - np.sum((xb / e[:2]) ** 2, axis=1)
        off_plane = inside & (disc > 0.0)
        Xb = np.zeros_like(Yb)
        Xb[off_plane, :2] = xb[off_plane]
        Xb[off_plane, 2] = e[2] * np.sqrt(disc[off_plane])
        Xb[~off_plane] = _closest_point_ellipse(e[:2], Yb[~off_plane][:, :2], E2)
        X[b] = Xb
    return X


def _closest_point_ellipse(e: np.ndarray, Y: np.ndarray, E2: np.ndarray) -> np.ndarray:
    """Closest points (M, 3) with x2 = 0 on the ellipse of semi-axes e (2,), e0 >= e1,
    to queries Y (M, 2) >= 0 (the 2-D case of the same construction)."""
    X = np.zeros((len(Y), 3))
    if len(Y) == 0:
        return X
    a = Y[:, 1] > 0.0
    if a.any():
        Ya = np.column_stack([Y[a], np.zeros(a.sum())])
        E2a = np.array([E2[0], E2[1], 1.0])  # third term inactive (y = 0)
        u = _shifted_root(E2a, Ya, np.full(a.sum(), E2[1]))
        X[a, :2] = E2[:2] * Y[a] / (u[:, None] + (E2[:2] - E2[1]))
    b = ~a
    if b.any():
        y0 = Y[b, 0]
        d = E2[0] - E2[1]
        x0 = np.where(d > 0.0, E2[0] * y0 / d if d > 0 else 0.0, np.inf)
        between = x0 < e[0]
        X[b, 0] = np.where(between, x0, e[0])
        X[b, 1] = np.where(between, e[1] * np.sqrt(np.clip(1.0 - (x0 / e[0]) ** 2, 0.0, None)), 0.0)
    return X
