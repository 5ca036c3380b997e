"""The robust ellipsoid fit (models.fit.robust_fit: Tukey's biweight on the Sampson
distance) with its reweighting spread over updates: the healthy globe under a local
model, at a bounded cost per A-scan.

Iteratively reweighted least squares (IRLS) needs every stored point's weight under the
current fit; RobustEllipsoidFit recomputes them all at once whenever the point count has
grown by 5 % (O(N) in one update: 1.5 ms at 20,000 points). Here one IRLS iteration is a
pass over the stored points in chunks: each step weighs a chunk more of them under the
current fit into the pass's scatter matrix, and the pass's end refits from it (the next
iterate), so a step costs O(chunk) whatever N, and the fit follows the data one pass
(N / chunk steps) behind. New points join the running pass weighted by the fit of their
arrival. A pass that leaves fewer than
`min_inlier_fraction` of the points any weight restarts from the plain fit (weights 1),
as RobustEllipsoidFit does, and the `iterations` passes after a restart run unchecked (as
its iterations after a restart do: IRLS from the plain fit needs a few to leave a
pathology out). Coordinates: the fits' (models.fit.ellipsoid_fit: origin at
the first point, lengths / LENGTH_SCALE_MM).

Bounded storage: past `max_stored` points every other stored point is dropped, and from
then on every `stride`-th point added is stored (the stride doubles at each thinning): a
regular subsample of the scan, so a pass costs at most max_stored rows whatever N and ends
every ~max_stored / chunk_per_point points added. IRLS from a start the pathology has
biased needs many passes: storing every point (a pass per 10 % more points), the globe of
the paper's staphyloma (seed 0) was still 470 um off at the end of the spiral; storing at
most 500 it is 111 um (the batch robust fit on every point: 109 um) from 79 % of the
spiral on (1,000: from 88 %; 250: from 69 %, but 118-130 um and the detached eye's 46 um
against 39 um). The subsample's noise costs a regular eye's globe 3-4 um of MAE (0.6 um
with every point), and the least-squares ellipsoid, on every point, is the global quadric
of the regular eyes.

How well the fit predicts: before points join (at the step after their add: a caller
adding one A-scan at a time steps once per packet, the per-call cost spread over it),
their biweight loss (Tukey's rho, (c^2 / 6) (1 - (1 - (d / c)^2)^3), c^2 / 6 beyond c)
under the current fit is averaged exponentially over about `memory` points
(`loss_mm2`), and the same of a rival sphere the caller names (`rival_loss_mm2`: the
model to beat, models.adaptive.model.AdaptiveEyeModel.global_for_local); a pathology's
points cost either model at most c^2 / 6 each. Both are also averaged over about
`hold_memory` points (`held_loss_mm2`, `held_rival_loss_mm2`): the caller that has taken
the globe up keeps it while it predicts better over that longer run, so that a patch the
sphere happens to fit (the retina by the ora serrata, seen as the tool goes in through a
port) does not swap the quadric for ~0.3 s. Every point received is scored, stored or
not: scored on the stored subsample alone, the memories held a handful of points late in
a long stream (at stride 512 the short one a single point), and on the staphyloma built
through a loop with every robot and sensor error but the calibration's (the faults
campaign's classes, seed 0, 140,533 A-scans) the last few stored points, all on the pouch,
cost both models the cap: the globe was given up at the end, and the local model's MAE
was 433 um (scanned p95 211 um) against 35 um (24 um) scoring every point.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from models.buffers import grown
from models.fit.ellipsoid_fit import LENGTH_SCALE_MM, EllipsoidFit, fit_of
from models.fit.quadric_kernels import design_row, fit_ellipsoid_scatter
from models.fit.quadric_residuals import sampson_one
from models.fit.robust_fit import RobustFitConfig, biweight_one, tukey_rho


@njit(cache=True)
def weigh_rows(S, X, w, i0, i1, v, has_fit, cutoff):
    """Weigh the scaled points X[i0:i1] by the biweight (biweight_one) of their Sampson
    distance from the quadric v (scaled units; cut-off `cutoff` scaled; weight 1 without a
    fit), write the weights to w[i0:i1] and add their weighted design rows to S (10, 10)'s
    upper triangle in place (the lower is its mirror: close_pass at the pass's end,
    half the work per point); returns how many got a weight > 0."""
    m = np.empty(10)
    inliers = 0
    for n in range(i0, i1):
        x, y, z = X[n, 0], X[n, 1], X[n, 2]
        wn = biweight_one(sampson_one(v, x, y, z), cutoff) if has_fit else 1.0
        w[n] = wn
        if wn <= 0.0:
            continue
        inliers += 1
        design_row(x, y, z, m)
        for i in range(10):
            a = wn * m[i]
            for j in range(i, 10):
                S[i, j] += a * m[j]
    return inliers


@njit(cache=True)
def close_pass(S, p0, scale, closed):
    """The running pass's end: S (10, 10) made symmetric from its upper triangle and kept in
    `closed` (10, 10), the ellipsoid fitted to it (fit_ellipsoid_scatter's (code, v, centre,
    semi-axes, rotation)) and S zeroed in place for the next pass."""
    for i in range(10):
        for j in range(i):
            S[i, j] = S[j, i]
    closed[:, :] = S
    fit = fit_ellipsoid_scatter(S, p0, scale, True)
    S[:, :] = 0.0
    return fit


@njit(cache=True)
def biweight_loss(X, i0, i1, v, cutoff):
    """Sum of tukey_rho (scaled units^2) of the points X[i0:i1]' Sampson distances from the quadric v."""
    s = 0.0
    for n in range(i0, i1):
        s += tukey_rho(sampson_one(v, X[n, 0], X[n, 1], X[n, 2]), cutoff)
    return s


@njit(cache=True)
def sphere_loss(X, i0, i1, c, r, cutoff):
    """Sum of tukey_rho (scaled units^2) of the points X[i0:i1]' distances from the sphere
    of centre c (3,) and radius r (scaled coordinates)."""
    s = 0.0
    for n in range(i0, i1):
        d0, d1, d2 = X[n, 0] - c[0], X[n, 1] - c[1], X[n, 2] - c[2]
        s += tukey_rho(np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) - r, cutoff)
    return s


@njit(cache=True)
def step_rows(S, X, w, i0, n, cursor, end, chunk, v, weighing, cutoff, scored, rival, c_mm, r_mm, p0, scale, F, m):
    """One step's compiled work (StreamingRobustFit.step): the points received since the
    last step, F[:m] (mm, every one whether stored or not; scaled in place like the stored
    points, (x - p0) / scale, when `scored`), their biweight losses under the fit v (when
    `scored`) and under the sphere of centre c_mm (3,) and radius r_mm, mm (when `rival`;
    scaled here too); the pending stored points X[i0:n]' weights, then the running pass's
    points X[cursor:min(cursor + chunk, end)]' (weigh_rows into S). Returns (loss, rival
    loss, points given a weight > 0, new cursor)."""
    c = np.empty(3)
    for i in range(3):
        c[i] = (c_mm[i] - p0[i]) / scale
    r = r_mm / scale
    if scored:  # F is the step's scratch: scaled in place, refilled from its start by the next add()
        for i in range(m):
            for j in range(3):
                F[i, j] = (F[i, j] - p0[j]) / scale
    loss = biweight_loss(F, 0, m, v, cutoff) if scored and m > 0 else 0.0
    rival_loss = sphere_loss(F, 0, m, c, r, cutoff) if scored and rival and m > 0 else 0.0
    inliers = weigh_rows(S, X, w, i0, n, v, weighing, cutoff) if n > i0 else 0
    if cursor < end:
        i1 = min(cursor + chunk, end)
        inliers += weigh_rows(S, X, w, cursor, i1, v, weighing, cutoff)
        cursor = i1
    return loss, rival_loss, inliers, cursor


_NO_CENTER = np.zeros(3)


class StreamingRobustFit:
    """Robust ellipsoid fit with the reweighting spread over updates (module doc).

    `add(P)` stores finite points P (N, 3) mm; `step(rival)` weighs the points added since
    the last step into the running pass, reweighs up to `chunk_per_point` x as many (at
    least `min_chunk`; less what `reweigh` did since the last step) stored points of the
    pass and, at its end, refits. `last_ok` the
    newest good EllipsoidFit (None before one); `loss_mm2` the exponential average (over
    about `memory` points) of the new points' biweight loss under the fit before they
    joined (mm^2; NaN before a fit), `rival_loss_mm2` the same of the Sphere `rival` the
    caller passes (the model to beat; NaN without one); `held_loss_mm2` and
    `held_rival_loss_mm2` the same over about `hold_memory` points; `passes` completed passes;
    `pending` points added since the last step; `last_step_weighed` the stored points
    reweighed from the step before to the last (by reweigh and the step); `close_due`
    whether a deferred step left a pass's refit to `close()`. At most `max_stored` points
    are kept (module doc: every `stride`-th point added); `n_points` the stored ones,
    `n_received` all added."""

    def __init__(self, config: RobustFitConfig | None = None, chunk_per_point: int = 10, min_chunk: int = 50,
                 memory: float = 400.0, max_stored: int = 500, hold_memory: float = 4000.0):
        self.config = RobustFitConfig() if config is None else config
        self.chunk_per_point, self.min_chunk, self.memory = int(chunk_per_point), int(min_chunk), float(memory)
        self.hold_memory = float(hold_memory)
        if not (np.isfinite(self.hold_memory) and self.hold_memory >= self.memory > 0):
            raise ValueError(f"hold_memory must be finite and >= memory = {self.memory:g} > 0, got {hold_memory}")
        if not (isinstance(max_stored, (int, np.integer)) and max_stored >= 2 * self.min_chunk):
            raise ValueError(f"max_stored must be an integer >= 2 min_chunk = {2 * self.min_chunk}, got {max_stored}")
        self.max_stored = int(max_stored)
        self.stride = 1  # every stride-th point added is stored
        self.n_received = 0
        self._received = 0  # points added since the last step (stored or not)
        self.p0: np.ndarray | None = None
        self.last_ok: EllipsoidFit | None = None
        self.passes = 0
        self.loss_mm2 = self.rival_loss_mm2 = self.held_loss_mm2 = self.held_rival_loss_mm2 = np.nan
        self._cut = self.config.cutoff_mm / LENGTH_SCALE_MM
        self._X = np.empty((1024, 3))
        self._w = np.empty(1024)
        self._F = np.empty((64, 3))  # the points received since the last step (mm), all scored at the step
        self._n = 0  # points stored
        self._taken = 0  # points weighed into the running pass (the rest are pending)
        self._next = np.zeros((10, 10))  # the running pass's scatter matrix
        self._closed = np.zeros((10, 10))  # a pass's, as it closes
        self.last_scatter = np.zeros((10, 10))  # the scatter matrix last_ok was fitted to
        self._cursor = self._end = 0  # the pass reweighs the points [0, end); later ones join it as they arrive
        self._inliers = 0  # points of the running pass with a weight > 0
        self._plain = True  # the running pass weighs every point 1 (no fit yet, or a restart)
        self._settling = 0  # passes left after a restart before the next may restart (`iterations`)
        self._v = np.zeros(10)
        self._ahead = 0  # stored points reweighed since the last step (reweigh), out of its budget
        self.close_due = False  # a step ended the running pass and left its refit to close()
        self.last_step_weighed = 0

    @property
    def n_points(self) -> int:
        return self._n

    @property
    def pending(self) -> int:
        """Points added since the last step (stored or not)."""
        return self._received

    @property
    def weights(self) -> np.ndarray:
        """(N,) every stored point's latest weight in [0, 1] (pending points: undefined)."""
        return self._w[:self._n]

    def _weighing(self) -> bool:
        return self.last_ok is not None and not self._plain

    def add(self, P: np.ndarray) -> None:
        """Store the finite points P (N, 3) mm, every stride-th one counted from the first
        (they join the running pass at the next step); past max_stored, every other stored
        point is dropped and the stride doubles (_thin)."""
        k = len(P)
        if k == 0:
            return
        if self.p0 is None:
            self.p0 = np.array(P[0], dtype=float)
        first = (-self.n_received) % self.stride  # the first of P whose count is a multiple of the stride
        m = self._received + k
        if m > len(self._F):
            self._F, = grown(self._received, m, self._F)
        self._F[self._received:m] = P  # the step's kernel scales them in place: no NumPy arithmetic per A-scan
        self.n_received += k
        self._received = m
        P = P[first::self.stride]
        k = len(P)
        if k == 0:
            return
        n = self._n + k
        if n > len(self._X):
            self._X, self._w = grown(self._n, n, self._X, self._w)
        self._X[self._n:n] = (P - self.p0) / LENGTH_SCALE_MM
        self._n = n
        while self._n > self.max_stored:
            self._thin()

    def _thin(self) -> None:
        """Keep every other stored point (those whose count is a multiple of twice the
        stride: the stream stays one regular subsample) and start the running pass again on
        them under the current fit (its scatter matrix held dropped points; an ended pass
        is refitted first)."""
        if self.close_due:
            self.close()
        n = self._n
        kept = (n + 1) // 2
        self._X[:kept] = self._X[0:n:2]
        self._w[:kept] = self._w[0:n:2]
        self._taken = (self._taken + 1) // 2  # the taken points precede the pending ones
        self._n = kept
        self.stride *= 2
        self._next = np.zeros((10, 10))
        self._cursor, self._end, self._inliers = 0, self._taken, 0

    def _score(self, loss: float, k: int, current: float, held: float) -> tuple[float, float]:
        """The averages over about `memory` and `hold_memory` added points, of which the
        last k scored `loss` (scaled units^2, a sum)."""
        loss *= LENGTH_SCALE_MM ** 2 / k
        if current != current:  # NaN: the first score
            return loss, loss
        return (current + min(k / self.memory, 1.0) * (loss - current),
                held + min(k / self.hold_memory, 1.0) * (loss - held))

    def reweigh(self, k: int) -> int:
        """Go on with the running pass between steps: up to chunk_per_point x k more of its
        stored points (k the points just added) weighed under the current fit, which changes
        only at a step's pass end, so they weigh as at the next step, and counted against
        that step's budget. A caller adding one A-scan at a time and stepping once per
        packet spreads the packet's reweighing over its A-scans. Returns how many."""
        cursor = self._cursor
        if cursor >= self._end or k <= 0:
            return 0
        i1 = min(cursor + self.chunk_per_point * k, self._end)
        self._inliers += weigh_rows(self._next, self._X, self._w, cursor, i1, self._v, self._weighing(), self._cut)
        self._cursor = i1
        self._ahead += i1 - cursor
        return i1 - cursor

    def step(self, rival=None, defer: bool = False) -> EllipsoidFit | None:
        """Score and weigh the pending points (against the fit and the Sphere `rival`), go on
        with the running pass; at its end, refit and start the next pass (the new fit, or
        None when no pass ended or the fit failed). With `defer`, a pass the step ends is
        refitted by close() instead (`close_due`): a caller adding one A-scan at a time puts
        the refit on the next A-scan, not on the one that steps."""
        if self.close_due:
            self.close()
        i0, n = self._taken, self._n
        k, received = n - i0, self._received
        self._received = 0
        scored, has_rival = self.last_ok is not None, rival is not None and received > 0
        cursor, ahead = self._cursor, self._ahead
        self._ahead = 0
        loss, rival_loss, inliers, self._cursor = step_rows(
            self._next, self._X, self._w, i0, n, cursor, self._end,
            max(max(self.min_chunk, self.chunk_per_point * received) - ahead, 0), self._v,
            self._weighing(), self._cut, scored, has_rival, rival.center if has_rival else _NO_CENTER,
            float(rival.radius) if has_rival else 0.0, _NO_CENTER if self.p0 is None else self.p0, LENGTH_SCALE_MM,
            self._F, received)
        if scored and received:  # every point received since the last step, whether stored or not
            self.loss_mm2, self.held_loss_mm2 = self._score(loss, received, self.loss_mm2, self.held_loss_mm2)
            if has_rival:
                self.rival_loss_mm2, self.held_rival_loss_mm2 = self._score(
                    rival_loss, received, self.rival_loss_mm2, self.held_rival_loss_mm2)
        if k:
            self._taken = n
        self._inliers += inliers
        self.last_step_weighed = self._cursor - cursor + ahead
        if self._cursor < self._end or n == 0:
            return None
        if defer:
            self.close_due = True
            return None
        return self.close()

    def close(self) -> EllipsoidFit | None:
        """End the running pass: refit from its scatter matrix and start the next pass over
        the points taken so far (the new fit, or None when the fit failed)."""
        self.close_due = False
        n = self._taken
        fit = fit_of(close_pass(self._next, self.p0, LENGTH_SCALE_MM, self._closed))
        self.passes += 1
        restart = not self._plain and self._settling == 0 and self._inliers < self.config.min_inlier_fraction * n
        self._settling = self.config.iterations if restart else max(self._settling - 1, 0)
        self._plain = restart or self.last_ok is None
        if fit.ok:
            self.last_ok, self._v = fit, fit.v
            self.last_scatter, self._closed = self._closed, self.last_scatter  # the fit's own rows: no copy
        self._cursor, self._end, self._inliers = 0, n, 0
        return fit if fit.ok else None
