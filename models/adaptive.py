"""The adaptive eye model: a sphere at first, an ellipsoid once the data supports it."""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from models._validation import as_points
from models.ellipsoid import Ellipsoid
from models.ellipsoid_fit import LENGTH_SCALE_MM, IncrementalEllipsoidFit, taubin_residual
from models.outlier_gate import GateState, OutlierGate
from models.robust_fit import RobustEllipsoidFit, RobustFitConfig
from models.scan_range import ScanRange
from models.sphere import Sphere
from models.sphere_kalman import SphereKalmanFilter
from models.transition import FitSnapshot, PaperCriteria


class ModelUpdate(NamedTuple):
    """One entry of the model history (mm, frame of the measured points).

    `n_points`: points in the model; `n_received`: points offered so far, including the
    non-finite and gated ones (so entries can be matched to A-scans);
    `criteria` maps each criterion name to (value, met); `ef_status` is "ok" or why the
    ellipsoid fit failed at this update (the previous good fit is kept). A NamedTuple:
    one is made per A-scan, so it must be cheap.
    """

    n_points: int
    kind: str
    scan_range_mm: float
    sf_residual_mm: float
    ef_residual_mm: float
    axis_change: float
    criteria: dict
    ef_status: str
    sphere_center: np.ndarray | None
    sphere_radius: float
    ellipsoid_center: np.ndarray | None
    ellipsoid_radii: np.ndarray | None
    ellipsoid_rotation: np.ndarray | None
    n_received: int = 0

    @property
    def sphere(self) -> Sphere | None:
        return None if self.sphere_center is None else Sphere(self.sphere_center, self.sphere_radius)

    @property
    def ellipsoid(self) -> Ellipsoid | None:
        if self.ellipsoid_center is None:
            return None
        return Ellipsoid(self.ellipsoid_center, self.ellipsoid_radii, self.ellipsoid_rotation)


class AdaptiveEyeModel:
    """Retina model from measured retinal points: sphere (Kalman filter) -> ellipsoid.

    `update(P)` absorbs a batch of points (N, 3) mm (any N, including one A-scan's
    point); non-finite points are skipped and counted in `n_rejected_nonfinite`; points
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

    def __init__(self, criteria=None, gate: OutlierGate | None = OutlierGate(), robust: RobustFitConfig | None = None):
        """`criteria`: PaperCriteria (default, the paper's) or PredictiveCriteria, or any
        object with the same `initial_state`/`evaluate` interface (models.transition);
        `gate`: the innovation gate against outliers (None: accept every finite point);
        `robust`: None for the paper's least-squares ellipsoid, or the settings of the
        robust one that down-weights pathological patches (models.robust_fit)."""
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
        self._prev_radii: np.ndarray | None = None
        self.kind = "sphere"
        self.transition_index: int | None = None
        self.n_rejected_nonfinite = 0
        self.history: list[ModelUpdate] = []
        self.last_accepted = np.zeros((0, 3))

    @property
    def n_points(self) -> int:
        return self._sf.n_points

    @property
    def sphere(self) -> Sphere | None:
        return self._sf.sphere

    @property
    def ellipsoid(self) -> Ellipsoid | None:
        last = self._ef.last_ok
        return None if last is None else last.ellipsoid

    @property
    def shape(self) -> Sphere | Ellipsoid | None:
        return self.ellipsoid if self.kind == "ellipsoid" else self.sphere

    @property
    def n_rejected_outliers(self) -> int:
        return 0 if self._gate is None else self._gate.n_rejected

    @property
    def scan_range_mm(self) -> float:
        return self._range.diameter_mm

    def update(self, P) -> ModelUpdate | None:
        """Absorb points P (N, 3) or (3,) mm; return this update's history entry (None, and
        no entry, if no point was finite and passed the gate)."""
        if isinstance(P, np.ndarray) and P.shape in ((3,), (1, 3)) and P.dtype == np.float64:
            P = P.reshape(1, 3)  # one A-scan's point: the per-A-scan path, checked in floats
            self.n_received += 1
            if not all(map(math.isfinite, P[0].tolist())):
                self.n_rejected_nonfinite += 1
                P = P[:0]
        else:
            P = as_points(P, "P", allow_nonfinite=True)
            self.n_received += len(P)
            finite = np.isfinite(P).all(axis=1)
            if not finite.all():
                self.n_rejected_nonfinite += int((~finite).sum())
                P = P[finite]
        if self._gate is not None:
            P = self._gate.admit(P, self._current, self._ef.p0, self.n_points)
        self.last_accepted = P
        if len(P) == 0:
            return None
        self._sf.absorb(P)
        self._ef.add(P)
        self._range.add(P)
        entry = self._evaluate(self._ef.fit())
        self.history.append(entry)
        return entry

    def _evaluate(self, fit) -> ModelUpdate:
        sf = self._sf.center_radius
        S = self._ef.S
        sf_res = ef_res = axis_change = np.nan
        v_sf = None
        V = np.empty((2, 10))  # the sphere's and the ellipsoid's quadrics, for one residual call
        if sf is not None:
            # the Kalman state [c, r^2 - |c|^2] is already in the fits' scaled coordinates
            # (both take the first point as origin): the sphere's quadric without a round trip
            cx, cy, cz, k = self._sf.state.tolist()
            V[0] = (1.0, 1.0, 1.0, 0.0, 0.0, 0.0, -cx, -cy, -cz, -k)
            v_sf = V[0]
        if fit.ok:
            if v_sf is None:
                ef_res = LENGTH_SCALE_MM * taubin_residual(S, fit.v)
            else:
                V[1] = fit.v
                sf_res, ef_res = (LENGTH_SCALE_MM * taubin_residual(S, V)).tolist()
            radii = sorted(fit.radii.tolist())
            if self._prev_radii is not None:
                axis_change = max(abs(a - b) / b for a, b in zip(radii, self._prev_radii))
            self._prev_radii = radii
        else:
            if v_sf is not None:
                sf_res = LENGTH_SCALE_MM * taubin_residual(S, v_sf)
            self._prev_radii = None
        snap = FitSnapshot(
            self.n_points, self._range.diameter_mm, sf_res, ef_res, axis_change, S, v_sf,
            fit.v if fit.ok else None, sf, (fit.center, fit.radii, fit.rotation) if fit.ok else None, self._ef.p0,
            self._ef.restarted_at, self._robust,
        )
        criteria, self._memory = self.criteria.evaluate(snap, self._memory)
        if self.kind == "sphere" and fit.ok and all(met for _, met in criteria.values()):
            self.kind = "ellipsoid"
            self.transition_index = len(self.history)
        elif self.kind == "ellipsoid" and self.criteria.reversible and self.criteria.wants_sphere(self._memory):
            self.kind = "sphere"
            self.transition_index = None
        last = self._ef.last_ok
        self._current = last.v if self.kind == "ellipsoid" and last is not None else v_sf
        return ModelUpdate(
            n_points=self.n_points,
            kind=self.kind,
            scan_range_mm=snap.scan_range_mm,
            sf_residual_mm=sf_res,
            ef_residual_mm=ef_res,
            axis_change=axis_change,
            criteria=criteria,
            ef_status=fit.status,
            sphere_center=None if sf is None else sf[0],
            sphere_radius=np.nan if sf is None else sf[1],
            ellipsoid_center=None if last is None else last.center,
            ellipsoid_radii=None if last is None else last.radii,
            ellipsoid_rotation=None if last is None else last.rotation,
            n_received=self.n_received,
        )
