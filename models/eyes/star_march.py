"""First crossings of rays with a star-shaped surface (models.eyes.radial): a march whose
steps are bounded by the radial function's slope, a bisection for excursions across the
surface between samples, then regula falsi (sub-nanometre). Compiled with numba: the
sensor casts rays on the true retina at 2 kHz. Units: mm, rad; frames W and E.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models.eyes.radial import inside_value, normal_inward
from models.shapes.rays import incidence_rad, rays_in_frame

CLIP_MM = 1e-5  # a ray's excursion across the surface shallower than this may go unseen (10 nm)
MARCH_STEP_MM = 0.05  # the ray march's shortest step (StarSurface.ray_cast)


@njit(cache=True)
def _on_ray(kind, p, o, d, t):
    """The inside value (mm) at o + t d (o, d: (3,) mm and unit)."""
    return inside_value(kind, p, o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2])


@njit(cache=True)
def _refine(kind, p, o, d, lo, hi, f_lo, f_hi, s0):
    """The crossing in [lo, hi] (mm along the ray; f_lo on the starting side s0, f_hi not)
    to ~1e-13 mm: regula falsi with the Illinois modification (superlinear: ~10
    evaluations instead of 60 halvings), halving where the secant leaves the bracket."""
    side = 0.0  # +1 / -1: which end moved last (Illinois halves the other's value)
    for _ in range(80):
        width = hi - lo
        if width <= 1e-13 * max(hi, 1.0):
            break
        den = f_hi - f_lo
        t = lo - f_lo * width / den if den != 0.0 else 0.5 * (lo + hi)
        if not (lo < t < hi):
            t = 0.5 * (lo + hi)
        f = _on_ray(kind, p, o, d, t)
        if np.sign(f) == s0:  # still on the starting side: t becomes the new lo
            if side == 1.0:
                f_hi *= 0.5
            lo, f_lo, side = t, f, 1.0
        else:
            if side == -1.0:
                f_lo *= 0.5
            hi, f_hi, side = t, f, -1.0
    return 0.5 * (lo + hi)


@njit(cache=True)
def _clip_search(kind, p, o, d, s0, lip, a, f_a, b, f_b):
    """(found, lo, f_lo, hi, f_hi): the first sign change in [a, b], whose ends are both on
    the side s0, by bisection, left half first. With |df/dt| <= lip, a part [l, r] with end
    values f_l, f_r holds no excursion deeper than CLIP_MM when lip (r - l) - |f_l| - |f_r|
    <= 2 CLIP_MM, and is not split further."""
    # depth first: the stack holds at most one part per level, and a part narrower than
    # 2 CLIP_MM / lip is never split (< 40 levels below a step of up to 2 r_out)
    stack = np.empty((64, 4))
    stack[0, 0], stack[0, 1], stack[0, 2], stack[0, 3] = a, f_a, b, f_b
    n = 1
    while n > 0:
        n -= 1
        l, f_l, r, f_r = stack[n, 0], stack[n, 1], stack[n, 2], stack[n, 3]
        if lip * (r - l) - abs(f_l) - abs(f_r) <= 2.0 * CLIP_MM:
            continue
        m = 0.5 * (l + r)
        f_m = _on_ray(kind, p, o, d, m)
        if np.sign(f_m) != s0:
            return True, l, f_l, m, f_m
        stack[n, 0], stack[n, 1], stack[n, 2], stack[n, 3] = m, f_m, r, f_r  # the right half waits
        stack[n + 1, 0], stack[n + 1, 1], stack[n + 1, 2], stack[n + 1, 3] = l, f_l, m, f_m
        n += 2
    return False, a, f_a, b, f_b


@njit(cache=True)
def _march(kind, p, o, d, s0, a, b, lip, step):
    """The first crossing (mm along the ray) in [a, b], NaN if none. From a sample with
    inside value f no crossing lies closer than |f| / lip, so the step is
    max(|f| / lip, step); a step whose end values leave room for an excursion deeper
    than CLIP_MM is searched by bisection."""
    t, f_t = a, _on_ray(kind, p, o, d, a)
    while t < b:
        t_next = min(t + max(abs(f_t) / lip, step), b)
        f_next = _on_ray(kind, p, o, d, t_next)
        if np.sign(f_next) != s0:
            return _refine(kind, p, o, d, t, t_next, f_t, f_next, s0)
        if s0 != 0.0:
            found, lo, f_lo, hi, f_hi = _clip_search(kind, p, o, d, s0, lip, t, f_t, t_next, f_next)
            if found:
                return _refine(kind, p, o, d, lo, hi, f_lo, f_hi, s0)
        t, f_t = t_next, f_next
    return np.nan


@njit(cache=True)
def ray_hits(kind, p, O, D, r_in, r_out, lip, step, t_max):
    """(M,) first crossings (mm) along the unit rays D (M, 3) from O (M, 3) mm, NaN where
    none lies within t_max. The surface lies in the shell r_in <= |x| <= r_out, so each
    ray is marched only where it runs in that shell (up to two parts, closed form)."""
    out = np.full(O.shape[0], np.nan)
    for m in range(O.shape[0]):
        o, d = O[m], D[m]
        s0 = np.sign(_on_ray(kind, p, o, d, 0.0))
        b = o[0] * d[0] + o[1] * d[1] + o[2] * d[2]
        oo = o[0] * o[0] + o[1] * o[1] + o[2] * o[2]
        disc_out = b * b - oo + r_out * r_out
        if disc_out <= 0.0:
            continue  # the line misses the shell's outer sphere
        end = min(-b + np.sqrt(disc_out), t_max)
        disc_in = b * b - oo + r_in * r_in
        enter_in, leave_in = np.inf, np.inf  # the part inside the ball of radius r_in
        if disc_in > 0.0:
            enter_in, leave_in = -b - np.sqrt(disc_in), -b + np.sqrt(disc_in)
        parts = ((max(-b - np.sqrt(disc_out), 0.0), min(enter_in, end)), (max(leave_in, 0.0), end))
        for lo, hi in parts:
            if lo < hi:
                out[m] = _march(kind, p, o, d, s0, lo, hi, lip, step)
                if not np.isnan(out[m]):
                    break
    return out


@njit(cache=True)
def star_hits(kind, p, O_W, U_W, p_WE, R_WE, r_in, r_out, lip, step):
    """((M,) distance mm along the unit rays (O_W, U_W) (M, 3) in W to the surface of the
    radial function (kind, p) placed at (R_WE (3, 3), p_WE (3,) mm), NaN without a hit or
    with one only at or behind the origin; (M,) incidence rad between the ray and the
    surface's normal at the hit, NaN without a hit): `ray_hits` (march constants r_in,
    r_out, lip of StarSurface.march_constants, step mm as in StarSurface.ray_cast) and
    `normal_inward` at the hit's direction from the centre, in one compiled pass (the
    composite eyes' kernel of models.eyes.retina_hits). ValueError as
    models.shapes.rays.rays_in_frame."""
    O, D = rays_in_frame(O_W, U_W, p_WE, R_WE)
    d = ray_hits(kind, p, O, D, r_in, r_out, lip, step, np.inf)
    incidence = np.full(O.shape[0], np.nan)
    for m in range(O.shape[0]):
        if not d[m] > 0.0:
            d[m] = np.nan
            continue
        x, y, z = O[m, 0] + d[m] * D[m, 0], O[m, 1] + d[m] * D[m, 1], O[m, 2] + d[m] * D[m, 2]
        r = np.sqrt(x * x + y * y + z * z)  # > r_in > 0: the surface lies in the shell
        n = normal_inward(kind, p, (x / r, y / r, z / r))
        incidence[m] = incidence_rad(n[0] * D[m, 0] + n[1] * D[m, 1] + n[2] * D[m, 2], 1.0)
    return d, incidence
