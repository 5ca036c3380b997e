"""Per-step true clearance of a run: the smallest signed distance (mm, > 0 inside) to the
true retina over each control step's monitored points, exact, from far fewer closest-point
searches than points.

A signed distance d is 1-Lipschitz: |d(p) - d(a)| <= |p - a|. The points of every
ANCHOR_EVERY-th step (and of the last) are searched; any other step's point then lies
between the bounds d(a) -/+ |p - a| from the same point at the anchor steps before and
after it. A step's smallest distance is at most the smallest upper bound U among its
points, so only points whose lower bound is <= U can hold it: those are searched, and
the step's minimum is the smallest searched value, bit for bit what searching every
point gives (each search depends on its own point only). Where the tip hovers at the
boundary two or three points of a step may qualify; far from it one does.
"""
from __future__ import annotations

import numpy as np

ANCHOR_EVERY = 10  # steps between anchor steps; about 1 in 4 of a 4-point step's searches remain


def true_clearances(points_W: list, true_eye) -> np.ndarray:
    """(M,) the smallest true clearance (mm, > 0 inside) of each step's points (k_i, 3) mm
    in W, with `true_eye.signed_distance` ((N, 3) mm -> (N,) mm) searched only where it
    can decide a step's minimum (module docstring), over each run of consecutive steps
    with the same number of points (the same points along the instrument). A step with
    a non-finite point: NaN."""
    out = np.full(len(points_W), np.nan)
    for good, P in _runs(points_W):
        out[good] = _run_minima(P, true_eye)
    return out


def bound_excess(points_W: list, bounds_mm: list, true_eye, caps_mm=(np.inf,)) -> list:
    """Per cap c of caps_mm: (largest excess mm, its step, the true clearance there mm) of
    the bounds the barrier assumed on the points' true clearance (bounds_mm: (k_i,) per
    step, +inf: none) over the true clearance, max over steps and the points whose bound is
    at most c of bound - true. Positive: at that step the retina lay nearer than the
    filter's rule took as certain. Searched as true_clearances searches (the same anchors):
    only where an excess can exceed the largest found at the anchors.
    (-inf, -1, nan) for a cap no bound meets."""
    caps = np.asarray(caps_mm, dtype=float)
    best, where = np.full(len(caps), -np.inf), [(-1, np.nan)] * len(caps)
    for good, P in _runs(points_W):
        B = np.array([bounds_mm[i] for i in good], dtype=float).reshape(P.shape[:2])
        counted = np.isfinite(B)[None] & (B[None] <= caps[:, None, None])  # (caps, m, K)
        if not counted.any():
            continue
        d, lower, _, is_anchor = _anchored(P, true_eye)
        at_anchor = is_anchor[None, :, None]
        known = counted & at_anchor
        found = [np.max(B[known[c]] - d[known[c]], initial=best[c]) for c in range(len(caps))]
        search = np.zeros(B.shape, dtype=bool)
        for c in range(len(caps)):
            open_ = counted[c] & ~is_anchor[:, None]
            search[open_] |= B[open_] - lower[open_] > found[c]
        if search.any():
            d[search] = np.asarray(true_eye.signed_distance(P[search]), dtype=float)
        for c in range(len(caps)):
            seen = counted[c] & np.isfinite(d)
            if not seen.any():
                continue
            excess = np.where(seen, B - np.where(seen, d, 0.0), -np.inf)
            k = int(np.argmax(excess))
            if excess.flat[k] > best[c]:
                best[c], where[c] = float(excess.flat[k]), (int(good[k // P.shape[1]]), float(d.flat[k]))
    return [(float(best[c]), *where[c]) for c in range(len(caps))]


def _runs(points_W: list):
    """(step indices, their points (m, K, 3)) per run of consecutive steps with the same
    number K > 0 of points, steps with a non-finite point left out."""
    counts = np.array([len(p) for p in points_W])
    if not len(counts):
        return
    P = np.vstack(points_W)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    finite = np.isfinite(P).all(axis=1)
    bad = ~np.logical_and.reduceat(finite, starts) if len(P) else np.zeros(len(counts), dtype=bool)
    edges = np.flatnonzero(np.diff(counts) != 0) + 1
    for lo, hi in zip(np.concatenate([[0], edges]), np.concatenate([edges, [len(counts)]])):
        good = np.flatnonzero(~bad[lo:hi]) + lo
        if counts[lo] == 0 or not len(good):
            continue
        K = counts[lo]
        rows = (starts[good][:, None] + np.arange(K)).ravel()
        yield good, P[rows].reshape(len(good), K, 3)


def _anchored(P: np.ndarray, true_eye) -> tuple:
    """(d, lower, upper, is_anchor) for steps' points P (M, K, 3) mm: d (M, K) the true
    signed distance at the anchor steps' points (+inf elsewhere), and every point's bounds
    on it from the anchors before and after (1-Lipschitz)."""
    M, K = P.shape[:2]
    anchors = np.unique(np.append(np.arange(0, M, ANCHOR_EVERY), M - 1))
    is_anchor = np.zeros(M, dtype=bool)
    is_anchor[anchors] = True
    d = np.full((M, K), np.inf)  # inf: not searched
    d[anchors] = np.asarray(true_eye.signed_distance(P[anchors].reshape(-1, 3)), dtype=float).reshape(-1, K)
    after = np.searchsorted(anchors, np.arange(M))  # the first anchor at or after each step
    before = anchors[np.maximum(after - 1, 0)]
    after = anchors[np.minimum(after, len(anchors) - 1)]
    gap_b = np.linalg.norm(P - P[before], axis=2)
    gap_a = np.linalg.norm(P - P[after], axis=2)
    lower = np.maximum(d[before] - gap_b, d[after] - gap_a)
    upper = np.minimum(d[before] + gap_b, d[after] + gap_a)
    return d, lower, upper, is_anchor


def _run_minima(P: np.ndarray, true_eye) -> np.ndarray:
    """(M,) the smallest signed distance (mm) of each step's points P (M, K, 3) mm: every
    point of the anchor steps searched, then the points whose lower bound does not
    exceed their step's smallest upper bound."""
    M, K = P.shape[:2]
    if M <= 2:
        return np.asarray(true_eye.signed_distance(P.reshape(-1, 3)), dtype=float).reshape(M, K).min(axis=1)
    d, lower, upper, is_anchor = _anchored(P, true_eye)
    search = ~is_anchor[:, None] & (lower <= upper.min(axis=1, keepdims=True))
    if search.any():
        d[search] = np.asarray(true_eye.signed_distance(P[search]), dtype=float)
    return d.min(axis=1)
