"""The adaptive eye model: a sphere at first, an ellipsoid once the data supports it."""
from __future__ import annotations

import copy
import math

import numpy as np

from models.adaptive.dwell import DWELL_MAX_POINTS, DWELL_RADIUS_MM, dwell_keep, new_state
from models.adaptive.global_sd import GlobalSd
from models.adaptive.history import History, ModelUpdate
from models.adaptive.outlier_gate import GateState, OutlierGate
from models.adaptive.scan_range import ScanRange
from models.adaptive.transition import FitSnapshot, PaperCriteria
from models.adaptive.update_kernel import (
    OUT_CENTER, OUT_RADII, OUT_ROTATION, OUT_SF_CENTER, OUT_SIZE, OUT_STATE, OUT_V_EF, OUT_V_SF, fit_summary, packet_update,
)
from models.fit.ellipsoid_fit import LENGTH_SCALE_MM, EllipsoidFit, IncrementalEllipsoidFit
from models.fit.eye_globe import EyeGlobe
from models.fit.quadric_kernels import FIT_STATUS
from models.fit.robust_fit import RobustEllipsoidFit, RobustFitConfig
from models.fit.streaming_robust import StreamingRobustFit
from models.fit.sphere_kalman import SphereKalmanFilter
from models.shapes.ellipsoid import Ellipsoid
from models.shapes.sphere import Sphere
from models.local.selection import LocalChoice
from models.shapes.validation import as_beams, as_points

EYE_RADII_MM = (8.0, 16.0)  # semi-axes of any plausible retina (human: 9.5-12.5 mm)
# The longest semi-axis of a plausible retina over its shortest: the catalog's per-dioptre
# growth (Atchison 2005, models.eyes.catalog.radii_for_refraction) gives 1.03 at -12 D,
# 1.13 emmetropic, 1.17 at +4 D and 1.225 at +8 D; every refraction from +9.6 D to the most
# myopic stays within 1.25. A globe fitted to a partial scan that a staphyloma fills is
# not: in the faults campaign (staphyloma, accel_limit, seed 0) one of 13.6 x 11.4 x 9.6 mm
# (1.42), fitted to 22 % of the reference region, lay up to 4 mm beyond the retina 30-90 deg
# from the data, where an eye's globe is trusted to 0.3 mm.
EYE_AXIS_RATIO_MAX = 1.25
GLOBE_MIN_SCAN_RANGE_MM = 10.0  # as PredictiveCriteria's: a smaller patch says nothing about the globe's shape
GLOBE_BATCH = 20  # points the robust globe takes per step (a sensor packet): its per-call overhead spread over them


def eyes_radii(r0: float, r1: float, r2: float) -> bool:
    """Whether semi-axes r0, r1, r2 (mm) are an eye's: each within EYE_RADII_MM and the
    longest at most EYE_AXIS_RATIO_MAX times the shortest (NaN is not). Three Python floats
    (`*radii.tolist()`), not an array or its NumPy scalars: np.min / np.max's dispatch was a
    third of global_for_local's time per A-scan, and comparing NumPy scalars takes 3.3 us
    per call against 1.3 us."""
    lo, hi = EYE_RADII_MM
    return (lo <= r0 <= hi and lo <= r1 <= hi and lo <= r2 <= hi
            and max(r0, r1, r2) <= EYE_AXIS_RATIO_MAX * min(r0, r1, r2))


class AdaptiveEyeModel:
    """Retina model from measured retinal points: sphere (Kalman filter) -> ellipsoid.

    `update(P)` absorbs a batch of points (N, 3) mm (any N, including one A-scan's
    point); non-finite points are skipped and counted in `n_rejected_nonfinite`; the
    A-scans of a beam held on one spot past models.adaptive.dwell's cap are skipped and
    counted in `n_dwelling` (they measure nothing new but their noise); points
    the innovation gate (`gate`, an OutlierGate; None disables it) finds too far from
    the current model are skipped and counted in `n_rejected_outliers`. Each
    call with at least one finite point is one update: the sphere filter and the
    ellipsoid scatter matrix absorb the points (O(1) each), the ellipsoid is refitted,
    and the transition criteria are evaluated; the model switches to the ellipsoid when
    they all hold (and back, for a reversible criterion that asks for it).
    `kind` is "sphere" or "ellipsoid"; `shape` the current Sphere or Ellipsoid (None
    before 4 points); `history` one ModelUpdate per update; `last_accepted` the points
    (K, 3) mm the last call took in (finite and past the gate).
    """

    def __init__(self, criteria=None, gate: OutlierGate | None = OutlierGate(), robust: RobustFitConfig | None = None,
                 local=None, wall_W=None):
        """`criteria`: PaperCriteria (default, the paper's) or PredictiveCriteria, or any
        object with the same `initial_state`/`evaluate` interface (models.adaptive.transition);
        `gate`: the innovation gate against outliers (None: accept every finite point);
        `robust`: None for the paper's least-squares ellipsoid, or the settings of the
        robust one that down-weights pathological patches (models.fit.robust_fit);
        `local`: None, or a models.local.grid.LocalRetinaModel that takes the same points on
        top of the global quadric (models.local.selection decides when it is used);
        `wall_W`: None or (K, 3) mm, known points of the eye wall in the frame of the points
        (the trocars' pivots), which the eye globe under the local model weighs
        (models.fit.eye_globe; with a local model only)."""
        self.criteria = PaperCriteria() if criteria is None else criteria
        self.gate = gate
        self._gate = None if gate is None else GateState(gate)
        self._current = None  # quadric of the current model, in the fits' scaled coordinates
        self.n_received = 0
        self._sf = SphereKalmanFilter()
        self._robust = robust is not None
        self._ef = RobustEllipsoidFit(robust) if self._robust else IncrementalEllipsoidFit()
        self._range = ScanRange()
        self._memory = self.criteria.initial_state()
        self._prev_radii = np.zeros(3)  # sorted semi-axes of the previous fit (mm), valid when _has_prev
        self._has_prev = False
        self.kind = "sphere"
        self.transition_index: int | None = None
        self.n_rejected_nonfinite = 0
        self.n_dwelling = 0  # A-scans of a beam held still, past the dwell rule's cap (models.adaptive.dwell)
        self._dwell = new_state()
        self._keep = np.empty(64, dtype=np.bool_)  # dwell_keep's verdicts, reused across updates
        self.history: History = History()  # of ModelUpdate; appended without copying the old entries
        self.last_accepted = np.zeros((0, 3))
        self.last_beams = None  # their beams' directions, when the update was given them and there is a local model
        self.local = local
        self.local_choice = LocalChoice() if local is not None else None
        self.globe = StreamingRobustFit() if local is not None else None
        self.globe_taken = False  # the robust globe is the quadric under the local model (_globe_taken)
        self._global_sd = GlobalSd()  # the sd far from the data of the ellipsoid under the local model
        self.eye_globe = EyeGlobe(EYE_RADII_MM, EYE_AXIS_RATIO_MAX, wall_W) if local is not None else None

    def __deepcopy__(self, memo) -> AdaptiveEyeModel:
        """An independent copy (it updates without touching this model) that shares the
        history's entries: an entry is never changed once made (each model appends its
        own), and copying the thousands of a spiral-built model's was ~50 ms of its ~53
        ms copy, once per scenario of a campaign (eval.experiments.boundary)."""
        new = object.__new__(type(self))
        memo[id(self)] = new
        for name, value in vars(self).items():
            setattr(new, name, value.copy() if name == "history" else copy.deepcopy(value, memo))
        return new

    @property
    def n_points(self) -> int:
        return self._sf.n_points

    @property
    def sphere(self) -> Sphere | None:
        """The sphere fit (mm, frame of the points): the same object until the model takes
        points (SphereKalmanFilter.sphere)."""
        return self._sf.sphere

    @property
    def ellipsoid(self) -> Ellipsoid | None:
        last = self._ef.last_ok
        return None if last is None else last.ellipsoid

    @property
    def shape(self) -> Sphere | Ellipsoid | None:
        return self.ellipsoid if self.kind == "ellipsoid" else self.sphere

    def global_for_local(self) -> Sphere | Ellipsoid | None:
        """The global quadric under the local model: the ellipsoid while the model is one
        and its semi-axes are an eye's (eyes_radii); else the robust globe
        (models.fit.streaming_robust) while it is taken up (_globe_taken); else, while the
        model is an ellipsoid that is no eye's, the eye globe (models.fit.eye_globe); else the sphere fit."""
        return self.quadrics_for_local()[0]

    def quadrics_for_local(self) -> tuple[Sphere | Ellipsoid | None, Ellipsoid | None, float | None]:
        """(global, trend, sd): the global quadric under the local model (global_for_local),
        the ellipsoid the transition criteria chose when that is not it (its semi-axes are
        no eye's, like the pointed eye's 177 x 31 x 31 mm fit to its posterior paraboloid),
        else None: the local model reads it next to the data and the global quadric far
        from them (models.local.config.LocalConfig.trend_deg), and the global quadric's own
        sd far from the data (mm) when it is an ellipsoid (models.adaptive.global_sd: its
        leverage and its gaps from the rivals the data do not rule out), else None (the
        local model's for its kind). Where that ellipsoid is no eye's and the robust globe
        is not taken, the global quadric is the eye globe (models.fit.eye_globe: the eye's
        ellipsoid nearest the data and the wall points) once fitted, with sd math.inf: a
        guess no better known than the sphere, whose prior the local model gives it. One
        look at the model's shape: this runs once per update."""
        ellipsoid = self.ellipsoid if self.kind == "ellipsoid" else None
        if ellipsoid is not None and eyes_radii(*ellipsoid.radii.tolist()):
            return ellipsoid, None, None if self.globe is None else self._global_sd.of_least_squares(self.globe)
        if self.globe_taken:
            return self.globe.last_ok.ellipsoid, ellipsoid, self._global_sd.of_globe(self.globe)
        if ellipsoid is not None and self.eye_globe is not None and self.eye_globe.ellipsoid is not None:
            return self.eye_globe.ellipsoid, ellipsoid, math.inf
        return self.sphere, ellipsoid, None

    @property
    def globe_sd_mm(self) -> float:
        """The robust globe's leverage sd far from the data, mm (models.adaptive.global_sd:
        GLOBE_SD_FACTOR x extrapolation_sd of its last fit; inf before one)."""
        return self._global_sd.leverage_mm

    def _globe_taken(self) -> bool:
        """Whether the robust globe is the quadric under the local model (after its step):
        its semi-axes are an eye's and the scan range at least GLOBE_MIN_SCAN_RANGE_MM, and
        it predicts the new points better than the sphere (a lower biweight loss: a
        pathology counts as much against either) over the last ~`memory` points, or, once
        taken, over the last ~`hold_memory` (models.fit.streaming_robust). Judged over the
        short memory alone, the quadric swaps between globe and sphere 7-10 times in each
        local plan of the detached eye and the staphyloma (seed 0), each time for 200-600
        A-scans as the tool enters through a port (the retina by the ora serrata, which the
        sphere fits better), and moves the boundary by up to 0.46 mm."""
        globe = self.globe
        fit = globe.last_ok
        if fit is None or self._range.diameter_mm < GLOBE_MIN_SCAN_RANGE_MM or not eyes_radii(*fit.radii.tolist()):
            return False
        return globe.loss_mm2 < globe.rival_loss_mm2 or (
            self.globe_taken and globe.held_loss_mm2 < globe.held_rival_loss_mm2)

    @property
    def level(self) -> str:
        """"local" while the local model is used (models.local.selection), else `kind`."""
        return "local" if self.local is not None and self.local_choice.active else self.kind

    @property
    def n_rejected_outliers(self) -> int:
        return 0 if self._gate is None else self._gate.n_rejected

    @property
    def scan_range_mm(self) -> float:
        return self._range.diameter_mm

    def update(self, P, beam_W=None) -> ModelUpdate | None:
        """Absorb points P (N, 3) or (3,) mm; return this update's history entry (None, and
        no entry, if no point was finite and passed the gate). `beam_W`: None or the
        A-scans' beam directions in W, one row per point (N, 3) or (3,): the local model
        measures each A-scan's share of a sample across its beam (LocalRetinaModel.update);
        last_beams holds those of last_accepted (None without them or without a local model).

        One compiled call does the update (models.adaptive.update_kernel.packet_update):
        the gate, the sphere filter, the scan range and, for the least-squares ellipsoid,
        the scatter matrix, the refit and the residuals; the robust fit (it reweights its
        points) takes the kept points after it. The sphere filter, the ellipsoid fit and
        the scan range all take the first point as their origin: ef.p0 stands for the three
        (set here from the kernel's when it took the first point)."""
        if not (type(P) is np.ndarray and P.dtype == _FLOAT64 and P.ndim in (1, 2) and P.shape[-1] == 3):
            P = as_points(P, "P", allow_nonfinite=True)
        if P.ndim == 1:
            P = P.reshape(1, 3)
        B = None if beam_W is None else as_beams(beam_W, len(P))
        if self.local is None:  # only the local model weighs by the beams
            B = None
        self.n_received += len(P)
        if len(self._keep) < len(P):
            self._keep = np.empty(len(P), dtype=np.bool_)
        keep = self._keep[:len(P)]
        taken = dwell_keep(P, self._dwell, DWELL_RADIUS_MM, DWELL_MAX_POINTS, keep)
        if taken < len(P):
            self.n_dwelling += len(P) - taken
            if taken == 0:
                self.last_accepted = np.zeros((0, 3))
                self.last_beams = None if B is None else np.zeros((0, 3))
                return None
            P = np.ascontiguousarray(P[keep])
            B = None if B is None else B[keep]
        sf, ef, scan, gate = self._sf, self._ef, self._range, self._gate
        n = sf.n_points  # the scan range's too: all three take the same points
        scan.reserve(len(P) + 1)  # the gate may add its pending first point
        g = _NO_GATE if gate is None else gate
        current = self._current
        out = np.empty(OUT_SIZE)
        kept = np.empty((len(P) + 1, 3))
        rows = np.empty(len(P) + 1, dtype=np.int64)
        p0 = np.zeros(3) if ef.p0 is None else ef.p0  # without a point yet: the kernel writes the first one
        refit = not self._robust  # the least-squares fit's refit is in the kernel; the robust one's below
        n_nonfinite, k, check, sf_ok, code, diameter, sf_res, ef_res, axis_change, radius = packet_update(
            P, n, p0, gate is not None, _NO_QUADRIC if current is None else current, current is not None,
            g.params, g.counts, g.last, g.scales, g.recent, sf.information, sf.information_vector, refit, ef.S,
            ef.spread_checked_at if refit else 0, ef.SPREAD_RECHECK if refit else 0, scan.X, scan.block_r,
            scan.diameter_mm, self._prev_radii, self._has_prev, LENGTH_SCALE_MM, kept, rows, out)
        self.n_rejected_nonfinite += n_nonfinite
        self.last_accepted = kept[:k]
        self.last_beams = None if B is None else B[rows[:k]]
        if k == 0:
            return None
        if ef.p0 is None:
            ef.p0, sf.p0, scan.p0 = p0, p0.copy(), p0.copy()
        if self.local is not None:
            self.globe.add(self.last_accepted)
            self._advance_globe(len(P), n + k, k)
            self._refit_eye_globe(n + k)
            self.local_choice.absorb(self.local, self.last_accepted, *self.quadrics_for_local(), self.last_beams)
        sf.took(k, out[OUT_STATE:OUT_V_SF] if sf_ok else None)
        scan.took(k, diameter)
        v_sf = out[OUT_V_SF:OUT_V_EF]
        if not refit:
            ef.add(self.last_accepted)
            fit = ef.fit()
            sf_res, ef_res, axis_change = fit_summary(
                ef.S, out[OUT_STATE:OUT_V_SF] if sf_ok else _NO_STATE, sf_ok, fit.v if fit.ok else _NO_QUADRIC, fit.ok,
                fit.radii if fit.ok else _NO_RADII, self._prev_radii, fit.ok and self._has_prev, v_sf, LENGTH_SCALE_MM)
        elif code:
            fit = ef.record(EllipsoidFit(FIT_STATUS[code]), check, took=k)
        else:  # centre, semi-axes and rotation in a read-only copy of their own: the Ellipsoid holds them (of_fit)
            ell = out[OUT_CENTER:OUT_SF_CENTER].copy()
            ell.flags.writeable = False
            r, R = OUT_RADII - OUT_CENTER, OUT_ROTATION - OUT_CENTER  # where the semi-axes and the rotation begin
            fit = ef.record(EllipsoidFit("ok", ell[:r], ell[r:R], ell[R:].reshape(3, 3), out[OUT_V_EF:OUT_CENTER]),
                            check, took=k)
        if sf_ok:
            return self._evaluate(fit, v_sf, (out[OUT_SF_CENTER:OUT_SIZE], radius), sf_res, ef_res, axis_change)
        return self._evaluate(fit, None, None, sf_res, ef_res, axis_change)

    def _advance_globe(self, received: int, n_points: int, k: int) -> None:
        """The robust globe's share of an update of `received` points, k of them kept,
        that brings the model to n_points: its step when due (_globe_steps), and the globe's
        take-up judged again after it. An update of one A-scan spreads a packet's work over
        the A-scans: it leaves a pass's refit to the next one (close) and, between steps,
        reweighs its share of the running pass (StreamingRobustFit.reweigh); packets do it
        all at their step."""
        globe, single = self.globe, received == 1
        if self._globe_steps(received, n_points):
            globe.step(self._sf.sphere, defer=single)
        elif globe.close_due:
            globe.close()
        elif globe.last_ok is not self._global_sd.fit:  # a single A-scan's: on the update after the fit's
            self._globe_sd(gaps=not single)
        elif single and self._global_sd.gaps_due:  # and its gaps on the next
            self._globe_sd(gaps=True, leverage=False)
        else:
            if single:
                globe.reweigh(k)
            return
        if not single and globe.last_ok is not self._global_sd.fit:
            self._globe_sd(gaps=True)
        self.globe_taken = self._globe_taken()

    def _refit_eye_globe(self, n_points: int) -> None:
        """Refit the eye globe (models.fit.eye_globe) when due, while the model is the
        ellipsoid the criteria chose, its semi-axes are no eye's and the robust globe is not
        taken: the case where it stands under the local model (quadrics_for_local)."""
        eg, ls = self.eye_globe, self._ef.last_ok
        if (self.kind != "ellipsoid" or self.globe_taken or ls is None or not eg.due(n_points)
                or eyes_radii(*ls.radii.tolist())):
            return
        sphere = self.sphere
        eg.refit(self._ef.S, self._ef.p0, n_points, sphere.center, sphere.radius, ls.rotation)

    def _globe_sd(self, gaps: bool, leverage: bool = True) -> None:
        """Measure the robust globe's last fit for the sd far from the data (GlobalSd): its
        `leverage` (5-9 us) and its `gaps` from the sphere and the least-squares ellipsoid
        as they are (8-12 us; make bench)."""
        if leverage:
            self._global_sd.measure_leverage(self.globe)
        if gaps:
            ls = self._ef.last_ok
            ls = ls if ls is not None and eyes_radii(*ls.radii.tolist()) else None
            self._global_sd.measure_gaps(self.globe, self.sphere, ls, self._ef.S, self._ef.p0)

    def _globe_steps(self, received: int, n_points: int) -> bool:
        """Whether the robust globe steps in an update of `received` points that brings the
        model to n_points: once it holds GLOBE_BATCH pending points, except that an update of
        fewer points (one A-scan's budget, not a packet's) that is also the criteria's
        checkpoint leaves it to the next update, unless it has waited that long already:
        the two heaviest pieces of work fall on different A-scans."""
        pending = self.globe.pending
        if pending < GLOBE_BATCH:
            return False
        if received >= GLOBE_BATCH or pending >= 2 * GLOBE_BATCH:
            return True
        due = getattr(self.criteria, "checkpoint_due", None)
        return due is None or not due(n_points, self._memory)

    def _evaluate(self, fit, v_sf, sf, sf_res: float, ef_res: float, axis_change: float) -> ModelUpdate:
        """The criteria, the transition and the history entry of an update whose fits are
        `fit` (the ellipsoid's EllipsoidFit), v_sf (the sphere's quadric in the fits' scaled
        coordinates) and sf (its centre mm, radius mm) (both None without a sphere), with
        residuals (mm) and axis change from fit_summary."""
        ok = fit.ok
        self._has_prev = ok
        ef = self._ef
        snap = FitSnapshot(
            self._sf.n_points, self._range.diameter_mm, sf_res, ef_res, axis_change, ef.S, v_sf, fit.v if ok else None,
            sf, (fit.center, fit.radii, fit.rotation) if ok else None, ef.p0, ef.restarted_at, self._robust)
        criteria, self._memory = self.criteria.evaluate(snap, self._memory)
        kind = self.kind
        if kind == "sphere":
            if ok and all(met for _, met in criteria.values()):
                self.kind = kind = "ellipsoid"
                self.transition_index = len(self.history)
        elif self.criteria.reversible and self.criteria.wants_sphere(self._memory):
            self.kind = kind = "sphere"
            self.transition_index = None
        last = ef.last_ok
        self._current = last.v if kind == "ellipsoid" and last is not None else v_sf
        entry = ModelUpdate(
            snap.n_points, kind, snap.scan_range_mm, sf_res, ef_res, axis_change, criteria, fit.status,
            None if sf is None else sf[0], np.nan if sf is None else sf[1],
            None if last is None else last.center, None if last is None else last.radii,
            None if last is None else last.rotation, self.n_received)
        self.history.append(entry)
        return entry


_FLOAT64 = np.dtype(np.float64)
_NO_GATE = GateState(OutlierGate())  # fills the compiled update's gate arguments when the gate is off (unread)
_NO_QUADRIC = np.zeros(10)  # stands for an absent quadric in compiled calls (read only with its flag)
_NO_STATE = np.zeros(4)
_NO_RADII = np.zeros(3)
