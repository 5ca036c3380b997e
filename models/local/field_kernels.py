"""Compiled kernels of the local retina model's field (models.local.field): the nodes'
quadratics blended over directions, the signed distance, gradient and standard deviation
at points, radii along directions, and the predictions the local model is chosen by
(models.local.selection). Radii mm from the fixed centre c0; directions unit vectors;
angles rad.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models.local.blend import MAX_CANDIDATES, N_SUMS, blend_many, candidates
from models.local.geometry import GLOBAL_SIZE, N_BASIS, N_COV, global_radius, node_frame
from models.shapes.field import unanswered

CAL_KNOTS_RAD = np.radians(np.array([0.0, 1.0, 2.0, 3.0, 5.0, 7.5, 10.0, 15.0]))  # the sd calibration's gaps
N_CAL = CAL_KNOTS_RAD.shape[0]


@njit(cache=True, inline="always")
def knot_at(gap):
    """(j, t): the gap `gap` rad lies between CAL_KNOTS_RAD[j] and [j + 1], a fraction t
    of the way (t = 1 at the last knot and beyond)."""
    last = CAL_KNOTS_RAD.shape[0] - 1
    if gap >= CAL_KNOTS_RAD[last]:
        return last - 1, 1.0
    j = 0
    while gap >= CAL_KNOTS_RAD[j + 1]:
        j += 1
    return j, (gap - CAL_KNOTS_RAD[j]) / (CAL_KNOTS_RAD[j + 1] - CAL_KNOTS_RAD[j])


@njit(cache=True, inline="always")
def calibrated_sd(sd, gap, cal):
    """The sd times the calibration's factor at `gap` rad from the data: cal (N_CAL,) the
    factors at CAL_KNOTS_RAD, linear between them (knot_at), the last one beyond
    (models.local.calibration measures them on the model's own predictions)."""
    j, t = knot_at(gap)
    return sd * (cal[j] + t * (cal[j + 1] - cal[j]))


@njit(cache=True)
def local_field(fp, P):
    """The barrier's FieldKernel kernel of a LocalField (models.local.field): the field's
    answers (field_at) in the barrier's form when fp carries a bound (fallback radius >
    0), else the model alone."""
    return field_at(fp, P, fp[BOUND + 4] > 0.0)


@njit(cache=True)
def local_model_field(fp, P):
    """The model alone (field_at without its bound), whatever bound fp carries: what a
    LocalField that is not the barrier answers, from the same params as the barrier."""
    return field_at(fp, P, False)


@njit(cache=True)
def field_at(fp, P, barrier):
    """(h (M,) mm, g (M, 3), u (M,) mm) of a LocalField's params fp at the points P (M, 3)
    mm. The surface is r = R(u) about the centre; h is the first-order signed distance
    F / |grad F| of F = R(u) - |p - c0| (the tangential gradients of R and u by forward
    differences of 1e-5 rad: three blends per point where central differences take five;
    their error, 1e-5 x the curvature / 2, is below 1e-3 mm/rad for curvatures under 200
    mm/rad^2, and the round-off of radii near 10 mm over 1e-5 rad ~1e-10 mm/rad; u's rate
    only in the barrier's form, which alone reads it), g = grad F / |grad F|, u the blended
    standard deviation.
    With `barrier` set (fp then holds the barrier's k and a fallback sphere, a
    conservative prior inside every retina: LocalField.with_fallback), a point answers
    the sphere's distance and no uncertainty wherever that allows more than h - k u (each
    is a bound on the true clearance; the larger holds), and elsewhere g is the gradient
    of the bound h - k u itself, g - k grad u (not a unit vector): the barrier's rate row
    then holds the bound's own rate, so a point moving along the surface towards
    directions the model knows less of (u growing) is held back as much as one moving
    towards the surface. Within the barrier's reach of the distance kept (h - k u under
    fp[BOUND + 5] + fp[BOUND + 6]) u is raised so that h - k u is the lowest of that bound and
    the bounds beside the point (lateral_bound). Below its bound (h - k u under the distance the filter keeps,
    fp[BOUND + 5]: d_safe and the calibration margin) g stays the distance's: the point
    recovers by moving away from the model's retina. Recovering along g - k grad u, a tip
    the model's update had left 0.66 mm of sigma slid 1.5 mm towards the retina, to 0.21
    mm of it, while the bound rose as sigma fell (`vitreoguard faults --shape detached`,
    class floaters, seed 0, scenario 42). NaN and +inf for a non-finite point; +inf, 0, 0 at every finite one for
    the field without a boundary (local flag -1)."""
    M = P.shape[0]
    if fp[2] < 0.0:  # no boundary
        return unanswered(P, np.full(M, np.inf), np.zeros((M, 3)), np.zeros(M))
    dirs, blend, local, c0, prior, gp, cal, x, cov, excess, has, near = unpack(fp)
    h, g, u = np.empty(M), np.empty((M, 3)), np.empty(M)
    eps = 1e-5
    cand = np.empty(MAX_CANDIDATES, dtype=np.int64)
    wide = np.empty(MAX_CANDIDATES, dtype=np.int64)  # lateral_bound's
    W, sums, blends = np.empty((3, 3)), np.empty((3, N_SUMS)), np.empty((3, 3))  # the point's three directions
    sin_nearest = np.sin(LATERAL_NEAREST * blend)  # a point r from c0 lies r sin_nearest or more from the look's rays
    for m in range(M):
        v0, v1, v2 = P[m, 0] - c0[0], P[m, 1] - c0[1], P[m, 2] - c0[2]
        r = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        if not np.isfinite(r):
            h[m] = g[m, 0] = g[m, 1] = g[m, 2] = np.nan
            u[m] = np.inf
            continue
        if r < 1e-9:
            v0, v1, v2, r = 0.0, 0.0, -1e-9, 1e-9
        u0, u1, u2 = v0 / r, v1 / r, v2 / r
        nc = candidates(dirs, u0, u1, u2, blend + 2.0 * eps, cand)
        e10, e11, e12, e20, e21, e22 = node_frame(u0, u1, u2)
        W[0, 0], W[0, 1], W[0, 2] = u0, u1, u2  # the point's direction, then a step along each tangent
        for s in range(2):
            a0, a1, a2 = (e10, e11, e12) if s == 0 else (e20, e21, e22)
            w0, w1, w2 = u0 + eps * a0, u1 + eps * a1, u2 + eps * a2
            q = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            W[1 + s, 0], W[1 + s, 1], W[1 + s, 2] = w0 / q, w1 / q, w2 / q
        blend_many(W, 3, dirs, blend, c0, gp, x, cov, excess, has, near, prior, cand, nc, sums, blends)
        R0, sd, gap = blends[0, 0], blends[0, 1], blends[0, 2]
        sd = calibrated_sd(sd, gap, cal)
        if local == 0.0:  # the global surface, uncertain by the local estimate's disagreement too
            S0 = _global_form_sd(sd, R0, c0, gp, u0, u1, u2)
        else:
            S0 = sd
        grad0, grad1, grad2 = 0.0, 0.0, 0.0
        gs0, gs1, gs2 = 0.0, 0.0, 0.0  # grad of the sd (it depends on the direction alone)
        for s in range(2):
            a0, a1, a2 = (e10, e11, e12) if s == 0 else (e20, e21, e22)
            Rp, Sp, gap = blends[1 + s, 0], blends[1 + s, 1], blends[1 + s, 2]
            dR = (Rp - R0) / eps  # mm per rad along the tangent a
            grad0 += dR * a0 / r
            grad1 += dR * a1 / r
            grad2 += dR * a2 / r
            if barrier:  # the sd's rate: only the barrier's form reads it
                Sp = calibrated_sd(Sp, gap, cal)
                if local == 0.0:
                    Sp = _global_form_sd(Sp, Rp, c0, gp, W[1 + s, 0], W[1 + s, 1], W[1 + s, 2])
                dS = (Sp - S0) / eps
                gs0, gs1, gs2 = gs0 + dS * a0 / r, gs1 + dS * a1 / r, gs2 + dS * a2 / r
        grad0, grad1, grad2 = grad0 - u0, grad1 - u1, grad2 - u2  # grad of R(u) - r
        gn = np.sqrt(grad0 * grad0 + grad1 * grad1 + grad2 * grad2)
        sd = S0
        if local == 0.0:
            R0 = global_radius(c0, gp, u0, u1, u2)
            grad0, grad1, grad2 = _global_gradient(c0, gp, u0, u1, u2, r, e10, e11, e12, e20, e21, e22, eps)
            gn = np.sqrt(grad0 * grad0 + grad1 * grad1 + grad2 * grad2)
        h[m] = (R0 - r) / gn
        g[m, 0], g[m, 1], g[m, 2] = grad0 / gn, grad1 / gn, grad2 / gn
        u[m] = sd
        rp = fp[BOUND + 4]
        if barrier:  # the barrier's form: the gradient of h - k u, or the fallback sphere's bound
            k = fp[BOUND]
            own = h[m] - k * sd
            # within the barrier's reach the bound looks beside the point, unless it is already below
            # the point's distance from every ray it would read (none can lower it)
            if k > 0.0 and r * sin_nearest < own <= fp[BOUND + 5] + fp[BOUND + 6]:
                lateral = lateral_bound(
                    r, u0, u1, u2, dirs, blend, c0, gp, x, cov, excess, has, near, prior, cal, local, k, wide)
                if lateral < own:
                    sd = (h[m] - lateral) / k
                    u[m] = sd
            w0, w1, w2 = fp[BOUND + 1] - P[m, 0], fp[BOUND + 2] - P[m, 1], fp[BOUND + 3] - P[m, 2]
            q = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            if rp - q > h[m] - k * sd and q > 0.0:  # the sphere, inside every retina: no uncertainty
                h[m], u[m] = rp - q, 0.0
                g[m, 0], g[m, 1], g[m, 2] = w0 / q, w1 / q, w2 / q
            elif h[m] - k * sd >= fp[BOUND + 5]:
                g[m, 0], g[m, 1], g[m, 2] = g[m, 0] - k * gs0, g[m, 1] - k * gs1, g[m, 2] - k * gs2
            # else: below its bound the point recovers along the distance's own gradient
    return h, g, u


LATERAL_RINGS = (0.75,)  # the rings of directions lateral_bound reads, in blends from the point's direction
LATERAL_AZIMUTHS = 4  # directions per ring (each further ring turned by half their spacing)
_PHI = 2.0 * np.pi * (np.arange(LATERAL_AZIMUTHS)[None, :] + 0.5 * np.arange(len(LATERAL_RINGS))[:, None]) / LATERAL_AZIMUTHS
LATERAL_TURNS = np.stack([np.cos(_PHI), np.sin(_PHI)], axis=-1)  # (rings, azimuths, 2): each direction's turn
LATERAL_REACH = max(LATERAL_RINGS)  # the outermost ring
LATERAL_NEAREST = min(LATERAL_RINGS)  # the innermost: a point is r sin(it x blend) or more from any ray the look reads


@njit(cache=True)
def lateral_bound(r, u0, u1, u2, dirs, blend, c0, gp, x, cov, excess, has, near, prior, cal, local, k, cand):
    """The smallest bound on the true distance from the point r u (from c0) to the retina
    over directions w beside u, LATERAL_AZIMUTHS on each ring of LATERAL_RINGS blends
    from it: along each w the retina lies no nearer the centre than the field's radius
    R(w) less k times its sd there (the global form's when `local` is 0, as field_at
    answers both: blend.blend_many, calibrated_sd, _global_form_sd), so the point is at least as
    far from it as from the nearest point of w beyond that radius (the point's foot on w
    where that radius lies below it). The bound at the point's
    own direction, h - k sigma, holds while the nearest retina lies along it; where a
    detachment's flank rises beside the point the nearest retina lies a few degrees off,
    where the field may know less (a detached eye's sphere phase with a 12 deg support:
    1.9-4.6 deg off, the field's error there 0.53-0.67 mm at sigma 0.20-0.37 mm against
    0.10 mm at the point). `cand`: a buffer for the nodes within a blend of the rings."""
    nc = candidates(dirs, u0, u1, u2, (LATERAL_REACH + 1.0) * blend + 1e-4, cand)
    e10, e11, e12, e20, e21, e22 = node_frame(u0, u1, u2)
    best = np.inf
    W, sums, blends = np.empty((LATERAL_AZIMUTHS, 3)), np.empty((LATERAL_AZIMUTHS, N_SUMS)), np.empty((LATERAL_AZIMUTHS, 3))
    for i in range(len(LATERAL_RINGS)):  # a ring's directions blended in one pass over the nodes
        theta = LATERAL_RINGS[i] * blend
        ct, st = np.cos(theta), np.sin(theta)
        for a in range(LATERAL_AZIMUTHS):
            t1, t2 = st * LATERAL_TURNS[i, a, 0], st * LATERAL_TURNS[i, a, 1]
            W[a, 0], W[a, 1], W[a, 2] = ct * u0 + t1 * e10 + t2 * e20, ct * u1 + t1 * e11 + t2 * e21, ct * u2 + t1 * e12 + t2 * e22
        blend_many(W, LATERAL_AZIMUTHS, dirs, blend, c0, gp, x, cov, excess, has, near, prior, cand, nc, sums, blends)
        for a in range(LATERAL_AZIMUTHS):
            w0, w1, w2 = W[a, 0], W[a, 1], W[a, 2]
            R, sd, gap = blends[a, 0], blends[a, 1], blends[a, 2]
            sd = calibrated_sd(sd, gap, cal)
            if local == 0.0:
                sd = _global_form_sd(sd, R, c0, gp, w0, w1, w2)
                R = global_radius(c0, gp, w0, w1, w2)
            t = max(R - k * sd, r * ct)  # the retina along w lies no nearer than R - k sd: the nearest
            best = min(best, np.sqrt(max(r * r + t * t - 2.0 * r * t * ct, 0.0)))  # of it, or the point's foot on w
    return best


@njit(cache=True, inline="always")
def _global_form_sd(sd, R, c0, gp, u0, u1, u2):
    """The sd of the global surface at the unit direction u where the blended field has
    radius R and sd `sd`: uncertain by the local estimate's disagreement with it too."""
    rg = global_radius(c0, gp, u0, u1, u2)
    return np.sqrt(sd * sd + (R - rg) * (R - rg))


@njit(cache=True, inline="always")
def _global_gradient(c0, gp, u0, u1, u2, r, e10, e11, e12, e20, e21, e22, eps):
    """grad (R_g(u) - r) at the point r u from c0 (central differences of eps rad)."""
    grad0, grad1, grad2 = -u0, -u1, -u2
    for s in range(2):
        a0, a1, a2 = (e10, e11, e12) if s == 0 else (e20, e21, e22)
        w0, w1, w2 = u0 + eps * a0, u1 + eps * a1, u2 + eps * a2
        q = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        Rp = global_radius(c0, gp, w0 / q, w1 / q, w2 / q)
        w0, w1, w2 = u0 - eps * a0, u1 - eps * a1, u2 - eps * a2
        q = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        Rm = global_radius(c0, gp, w0 / q, w1 / q, w2 / q)
        dR = (Rp - Rm) / (2.0 * eps * r)
        grad0, grad1, grad2 = grad0 + dR * a0, grad1 + dR * a1, grad2 + dR * a2
    return grad0, grad1, grad2


BOUND_SIZE = 7  # [k, fallback centre (3), fallback radius, the distance kept below which a point recovers, reach]
HEAD = 6 + 8 + GLOBAL_SIZE + N_CAL + BOUND_SIZE  # n, blend, local, c0 (3), prior (8), global (16), sd calibration, bound
CAL = 14 + GLOBAL_SIZE  # where the sd calibration's factors begin
BOUND = HEAD - BOUND_SIZE  # where the bound block begins (fallback radius 0: none)
PER_NODE = 3 + N_BASIS + N_COV + 3  # unpack's numbers per node: direction, quadratic, covariance, excess, has, near


@njit(cache=True)
def unpack(fp):
    """(dirs (n, 3), blend rad, local flag, c0 (3,), prior (8,), global (16,), sd calibration
    (N_CAL,), x (n, 6), cov (n, 21), excess (n,), has (n,), near (n,): the cosine of each
    node's nearest data angle) of a LocalField's params."""
    n = int(fp[0])
    o = HEAD
    dirs = fp[o:o + 3 * n].reshape((n, 3))
    o += 3 * n
    x = fp[o:o + N_BASIS * n].reshape((n, N_BASIS))
    o += N_BASIS * n
    cov = fp[o:o + N_COV * n].reshape((n, N_COV))
    o += N_COV * n
    return (dirs, fp[1], fp[2], fp[3:6], fp[6:14], fp[14:CAL], fp[CAL:BOUND], x, cov, fp[o:o + n], fp[o + n:o + 2 * n],
            fp[o + 2 * n:o + 3 * n])


@njit(cache=True)
def radii_at(dirs, blend, local, c0, prior, gp, cal, x, cov, excess, has, near, U):
    """(M,) radius (mm) and (M,) calibrated standard deviation (mm) of the blended field
    along the unit directions U (M, 3) from c0 (blend.blend_many per row); with `local` 0 the
    global surface's, as local_field answers it (_global_form_sd)."""
    cand = np.empty(MAX_CANDIDATES, dtype=np.int64)
    sums, blends = np.empty((1, N_SUMS)), np.empty((1, 3))
    R, S = np.empty(U.shape[0]), np.empty(U.shape[0])
    for m in range(U.shape[0]):
        u0, u1, u2 = U[m, 0], U[m, 1], U[m, 2]
        nc = candidates(dirs, u0, u1, u2, blend, cand)
        blend_many(U[m:m + 1], 1, dirs, blend, c0, gp, x, cov, excess, has, near, prior, cand, nc, sums, blends)
        R[m], sd, gap = blends[0, 0], blends[0, 1], blends[0, 2]
        S[m] = calibrated_sd(sd, gap, cal)
        if local == 0.0:
            S[m] = _global_form_sd(S[m], R[m], c0, gp, u0, u1, u2)
            R[m] = global_radius(c0, gp, u0, u1, u2)
    return R, S


@njit(cache=True)
def predictions(P, c0, gp, gate, dirs, blend, prior, x, cov, excess, has, near, out):
    """Each point of P (M, 3) mm predicted along its direction from c0 before it is absorbed:
    out (M, 6) rows [measured radius, the local field's radius, its uncalibrated sd (mm),
    its gap (rad: blend.blend_many), the global quadric's radius (mm), the angle from the data of
    the node nearest the point (rad)], for the points absorb_points
    would take (gate); NaN rows for the others. Returns out. What the local model is
    chosen by (models.local.selection) and its sd calibrated on
    (models.local.calibration): the data's own held-out errors."""
    cand = np.empty(MAX_CANDIDATES, dtype=np.int64)
    W, sums, blends = np.empty((1, 3)), np.empty((1, N_SUMS)), np.empty((1, 3))
    for i in range(P.shape[0]):
        out[i, :] = np.nan
        v0, v1, v2 = P[i, 0] - c0[0], P[i, 1] - c0[1], P[i, 2] - c0[2]
        r = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
        if not (np.isfinite(r) and gate[0] <= r <= gate[1]):
            continue
        u0, u1, u2 = v0 / r, v1 / r, v2 / r
        rg = global_radius(c0, gp, u0, u1, u2)
        if not abs(r - rg) <= gate[2]:
            continue
        nc = candidates(dirs, u0, u1, u2, blend, cand)
        best, nearest = -2.0, np.nan  # the nearest node's angle from the data
        for j in range(nc):
            c = u0 * dirs[cand[j], 0] + u1 * dirs[cand[j], 1] + u2 * dirs[cand[j], 2]
            if c > best:
                best, nearest = c, np.arccos(max(min(near[cand[j]], 1.0), -1.0))
        W[0, 0], W[0, 1], W[0, 2] = u0, u1, u2
        blend_many(W, 1, dirs, blend, c0, gp, x, cov, excess, has, near, prior, cand, nc, sums, blends)
        rl, sd, gap = blends[0, 0], blends[0, 1], blends[0, 2]
        out[i, 0], out[i, 1], out[i, 2], out[i, 3], out[i, 4], out[i, 5] = r, rl, sd, gap, rg, nearest
    return out
