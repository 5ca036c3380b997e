"""The adaptive model as a Drake system: each sensor packet updates the model (with its
valid samples, but those whose beam grazes the filter's model), and the filter reads a
snapshot (the model's shape in W, its phase, its coverage, and through its time the
sensor's freshness: sensor -> model -> filter).

Before the model has a shape the conservative prior eye (safety.margins) bounds the
motion. Units: mm, s; frame W.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from models import AdaptiveEyeModel
from models.adaptive.coverage import DirectionCoverage
from models.adaptive.transition import PredictiveCriteria
from models.local.grid import LocalRetinaModel
from models.shapes.rays import beam_incidences_rad
from planning.iioct import NO_SAMPLE_YET
from planning.iioct.stream import WHY, StreamHealth
from safety.margins import UncertaintyMargins

ASCAN_LOG_EVERY = 100  # log one A-scan in 100 ("ascan" sensor mode): 20 Hz of the 2 kHz stream, ~0.4 MB/s
MODEL_LOG_PERIOD_S = 0.05  # /model and /oct/points at 20 Hz of simulation time (and at every change of kind)


@dataclass
class LogThrottle:
    """What the model system gathered for the log since its last /model and /oct/points
    messages: the accepted point arrays, the newest model entry, and the time (s) and model
    kind of the last messages."""

    points: list = field(default_factory=list)
    entry: object = None
    last_t_s: float = -np.inf
    last_kind: str | None = None


class ModelSnapshot(NamedTuple):
    """What the filter reads of the model: `kind` "prior" | "sphere" | "ellipsoid", its
    `shape` in W (None for the prior), `t_s` of the newest sensor sample the model system
    has processed (it stamps every packet: the filter's model age and sensor age), the
    model's RMS residual (mm) and point count; `healthy_t_s` the newest HEALTHY sample's
    time (planning.iioct.stream: the filter's sensor age) and `stream` what the samples
    since were ("" while healthy)."""

    kind: str
    shape: object
    t_s: float
    residual_mm: float
    n_points: int
    coverage: object = None  # models.adaptive.coverage.CoverageView of the measured directions
    field: object = None  # models.local.field.LocalField the filter keeps to (with the local model), else None
    healthy_t_s: float = 0.0
    stream: str = ""

    def __deepcopy__(self, memo) -> ModelSnapshot:
        return self  # immutable (the shapes are frozen): Drake copies abstract state values often

    def margin_mm(self, margins: UncertaintyMargins) -> float:
        """The uncertainty margin (mm) the filter adds to d_safe for this model (none for
        the prior, which is conservative by construction)."""
        return margins.margin_mm(None if self.shape is None else self.kind, self.residual_mm)


_PRIOR_AT_0 = ModelSnapshot("prior", None, 0.0, np.nan, 0)


def semi_axes_mm(shape) -> np.ndarray:
    """The semi-axes (mm) of a Sphere (its radius, once) or an Ellipsoid."""
    return np.atleast_1d(getattr(shape, "radii", getattr(shape, "radius", np.nan)))


def snapshot_of(model: AdaptiveEyeModel, coverage: DirectionCoverage, t_s: float, min_points: int = 0,
                min_scan_range_mm: float = 0.0, radius_range_mm: tuple = (0.0, np.inf), bound=None) -> ModelSnapshot:
    """The snapshot of `model` at t_s: its current shape once it rests on at least
    `min_points` points over `min_scan_range_mm` with semi-axes within `radius_range_mm`;
    an ellipsoid outside that range (a fit to a pathological eye, like the pointed eye's
    153 x 29 x 29 mm) gives way to the model's sphere fit if that one is an eye's (its
    phase's wider margin applies); "prior" otherwise. The model's shapes are made once
    per update (AdaptiveEyeModel.shape), and only once the trust limits on points and
    scan range are met; the coverage view is rebuilt only as DirectionCoverage.view says.
    With a local model (model.local) the trusted snapshot also holds its LocalField, and
    its kind is "local" while the model uses its local correction (model.level), its
    params holding the barrier's `bound` (sigma_factor, fallback Sphere) if given
    (LocalRetinaModel.field)."""
    n = model.n_points
    if model.local is not None:
        return _local_snapshot(model, coverage, t_s, min_points, min_scan_range_mm, radius_range_mm, bound)
    shape = None if n < min_points or model.scan_range_mm < min_scan_range_mm else model.shape
    if shape is not None:
        last, (lo, hi) = model.history[-1], radius_range_mm
        if model.kind == "ellipsoid":
            radii = shape.radii.tolist()
            if lo <= min(radii) and max(radii) <= hi:
                return ModelSnapshot("ellipsoid", shape, t_s, float(last.ef_residual_mm), n, coverage.view(shape))
            shape = model.sphere  # the ellipsoid is no eye's: its sphere fit, if that one is
        if shape is not None and lo <= shape.radius <= hi:
            return ModelSnapshot("sphere", shape, t_s, float(last.sf_residual_mm), n, coverage.view(shape))
    return ModelSnapshot("prior", None, t_s, float("nan"), n, coverage.view())


def _local_snapshot(model, coverage, t_s, min_points, min_scan_range_mm, radius_range_mm, bound) -> ModelSnapshot:
    """snapshot_of for a model with a local part: the trust limits on points, scan range
    and the global quadric's semi-axes as for the quadric, then the LocalField."""
    n = model.n_points
    shape = model.global_for_local()
    lo, hi = radius_range_mm
    if (shape is None or n < min_points or model.scan_range_mm < min_scan_range_mm or model.local.global_params is None
            or not (lo <= float(np.min(semi_axes_mm(shape))) and float(np.max(semi_axes_mm(shape))) <= hi)):
        return ModelSnapshot("prior", None, t_s, float("nan"), n, coverage.view())
    level = model.level
    kind = level if level == "local" else type(shape).__name__.lower()
    last = model.history[-1]
    residual = float(last.ef_residual_mm if kind == "ellipsoid" else last.sf_residual_mm)
    return ModelSnapshot(kind, shape, t_s, residual, n, coverage.view(),
                         model.local.field(level == "local", kind, bound))


class AdaptiveModelSystem(LeafSystem):
    """Feeds each packet of sensor samples (input "packet", a planning.iioct
    SensorPacket, its samples in time order as IioctSensorSystem delivers them) to an
    AdaptiveEyeModel: one update per packet with the valid points of its samples not
    seen before; state and output "snapshot" (ModelSnapshot). Runs at the packet rate,
    just after each packet is complete. Logs the distances and model updates when a
    logger is set. `field_bound` (sigma_factor, fallback Sphere, keep_mm) or None: the filter's
    barrier bound, written into a local model's field (LocalRetinaModel.field) so that
    the filter's barrier form of it shares its params.

    `max_incidence_rad` (or None: every valid sample): once the filter has a model (the
    snapshot's quadric), a valid sample whose beam meets it more obliquely is not taken
    into the model or its coverage (`n_oblique` counts them): beyond the iiOCT sensor's
    own limit (planning.iioct.sensor, 55 deg) the extractor's distances are wrong but
    confident (models.iioct.error_model, the retina 3-6 mm ahead: bias 0.10-0.36 mm and
    SD 0.12-0.47 mm along the beam at 60-66 deg, against at most 0.021 and 0.014 mm at
    40-55 deg). The stream's health still counts the sample: the sensor sees retina."""

    def __init__(self, packet_rate_hz: float, offset_s: float, min_points: int, min_scan_range_mm: float,
                 radius_range_mm: tuple, field_bound=None, max_incidence_rad: float | None = None):
        super().__init__()
        self._trust = (min_points, min_scan_range_mm, radius_range_mm)
        self._bound = field_bound
        self._max_incidence_rad = max_incidence_rad
        self._packet = self.DeclareAbstractInputPort("packet", AbstractValue.Make(NO_SAMPLE_YET))
        self._snap = self.DeclareAbstractState(AbstractValue.Make(_PRIOR_AT_0))
        self.DeclarePeriodicUnrestrictedUpdateEvent(1.0 / packet_rate_hz, offset_s, self._update)
        self.DeclareStateOutputPort("snapshot", self._snap)
        self.on_snapshot = None  # None, or a callable given each new snapshot (kept across runs: its setter clears it)
        self._compile()
        self.reset(AdaptiveEyeModel(), DirectionCoverage(np.zeros(3)))

    def _compile(self) -> None:
        """Compile (or load from numba's cache, ~0.5 s) the model's kernels before any run, so
        that no run's first packet holds it: a throwaway model with the predictive criteria
        (their checkpoints' kernels too) and its coverage take packets of 10 points from an
        eye-sized ellipsoid cap (mm) until both fits and a checkpoint's convergence test
        have run, then the snapshot of each kind (trust limits of 0: any shape) and its
        field's answer at two points (its first use otherwise: ~9 s into a first run's scan)."""
        rng = np.random.default_rng(0)
        u = rng.normal(size=(300, 3))
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        u[:, 2] = -np.abs(u[:, 2])  # a posterior cap
        P = u * [11.5, 11.4, 10.1] + rng.normal(0.0, 0.02, (300, 1)) * u
        model = AdaptiveEyeModel(criteria=PredictiveCriteria(), local=LocalRetinaModel(np.zeros(3)))
        coverage = DirectionCoverage(np.zeros(3))
        for k in range(0, len(P), 10):
            model.update(P[k:k + 10])
            coverage.add(model.last_accepted)
        for shape in (None, model.sphere, model.ellipsoid):
            coverage.view(shape)
        snap = snapshot_of(model, coverage, 0.0)
        model.local.params(True)
        if snap.field is not None:  # the field as the model answers it (the filter compiles its barrier form)
            snap.field.signed_distance_gradient_uncertainty(P[:2])

    def reset(self, model: AdaptiveEyeModel, coverage: DirectionCoverage, logger=None) -> None:
        self.model, self.coverage, self.logger = model, coverage, logger
        self._last_t = -np.inf
        self._written = _PRIOR_AT_0  # the declared state's value, until initial_snapshot
        self.wall_s = 0.0  # wall time (s) of its updates since the reset
        self.observer_wall_s = 0.0  # of it, on_snapshot's (left out of wall_s)
        self.update_us: list[float] = []
        self._distances: list[tuple] = []  # per packet: its extracted and true distances, and which are valid
        self.n_samples = 0
        self.n_invalid = 0
        self.n_oblique = 0  # valid samples not taken for their incidence on the model (max_incidence_rad)
        self.epochs: list[ModelSnapshot] = []  # the snapshot whenever the filter's model changed kind
        self.health = StreamHealth()
        self.health.healthy_t_s = 0.0  # the run's start: the sensor has the filter's age limit to deliver
        self._seen = None  # the last packet read
        self._throttle = LogThrottle()

    def _oblique(self, packet, valid: np.ndarray) -> np.ndarray:
        """(M,) bool: the `valid` samples of `packet` whose reported beams meet the
        snapshot's shape more obliquely than max_incidence_rad."""
        out = np.zeros(len(valid), dtype=bool)
        out[valid] = beam_incidences_rad(self._written.shape, packet.beam_origin_W[valid],
                                         packet.beam_dir_W[valid]) > self._max_incidence_rad
        return out

    def _log_model(self, entry) -> None:
        """Gather the points the model took in and its newest update; log them (/oct/points,
        /model) once MODEL_LOG_PERIOD_S of simulation time has passed since the last time,
        or at once when the model's kind changed."""
        th = self._throttle
        if len(self.model.last_accepted):
            th.points.append(self.model.last_accepted)
        changed = entry is not None and entry.kind != th.last_kind
        if entry is not None:
            th.entry = entry
        if changed or self._last_t - th.last_t_s >= MODEL_LOG_PERIOD_S:
            self.flush_log()

    def flush_log(self) -> None:
        """Log what _log_model gathered (at the end of a run: nothing it took in goes unlogged)."""
        th = self._throttle
        if self.logger is None or self.logger.closed:
            return
        if th.points:
            self.logger.log_points(self._last_t, np.vstack(th.points))
        if th.entry is not None:
            self.logger.log_model_update(self._last_t, th.entry)
            th.last_kind = th.entry.kind
        th.points, th.entry, th.last_t_s = [], None, self._last_t

    @property
    def errors_mm(self) -> list[float]:
        """Extracted - true distance (mm) of the valid samples since the reset, in time order
        (evaluation; made when read from the packets' arrays, which no one changes)."""
        return [e for d, true, valid in self._distances for e in (d - true)[valid].tolist()]

    def _mark_epoch(self, snap: ModelSnapshot) -> None:
        if not self.epochs or self.epochs[-1].kind != snap.kind:
            self.epochs.append(snap)

    def snapshot_for(self, model: AdaptiveEyeModel, coverage: DirectionCoverage, t_s: float) -> ModelSnapshot:
        """What the filter would read of `model` at t_s under this loop's trust rules."""
        return snapshot_of(model, coverage, t_s, *self._trust, bound=self._bound)

    def initial_snapshot(self) -> ModelSnapshot:
        """The snapshot the run starts from (ClosedLoop.run puts it in the context's state)."""
        self._written = self.snapshot_for(self.model, self.coverage, 0.0)
        self._mark_epoch(self._written)
        return self._written

    def _update(self, context, state) -> None:
        t0, observed = time.perf_counter(), self.observer_wall_s
        self._absorb(context, state)
        self.wall_s += time.perf_counter() - t0 - (self.observer_wall_s - observed)

    def _health(self, packet, state) -> None:
        """Judge the packet's samples (planning.iioct.stream.StreamHealth); a packet read
        before is no packet. The state carries the verdict even when the model is not updated."""
        health = self.health
        if packet is self._seen:
            if packet is not NO_SAMPLE_YET:
                health.why = WHY["dropout"]
        else:
            self._seen = packet
            health.update(packet.t_s, packet.valid, packet.distance_mm)
        w = self._written
        if w.healthy_t_s != health.healthy_t_s or w.stream != health.why:
            self._written = w._replace(healthy_t_s=health.healthy_t_s, stream=health.why)
            state.get_mutable_abstract_state(0).set_value(self._written)

    def _absorb(self, context, state) -> None:
        packet = self._packet.Eval(context)
        self._health(packet, state)
        if not packet.t_s.item(0) > self._last_t:  # samples seen before (or the placeholder before the first packet)
            new = np.flatnonzero(packet.t_s > self._last_t)  # in time order: the packet's last ones
            if not len(new):
                return
            packet = packet.take(new)
        T, valid = packet.t_s, packet.valid
        self._last_t = T.item(-1)
        first = self.n_samples
        self.n_samples += len(T)
        n_valid = valid.tolist().count(True)  # C calls only (np.count_nonzero is a Python function)
        self.n_invalid += len(T) - n_valid
        self._distances.append((packet.distance_mm, packet.true_distance_mm, valid))
        if self.logger is not None:
            self.logger.log_distances(T.tolist(), packet.distance_mm.tolist(), valid.tolist(), packet.confidence.tolist())
            ascans = packet.ascans
            if ascans is not None:
                for k, (t, ok) in enumerate(zip(T.tolist(), valid.tolist())):
                    if ascans[k] is not None and (first + k) % ASCAN_LOG_EVERY == 0:
                        self.logger.log_ascan(t, ascans[k], ok, packet.reasons[k])
        entry = None
        if n_valid and self._max_incidence_rad is not None and self._written.shape is not None:
            valid = valid & ~self._oblique(packet, valid)
            n_taken = valid.tolist().count(True)
            self.n_oblique += n_valid - n_taken
            n_valid = n_taken
        if n_valid:
            t0 = time.perf_counter()
            whole = n_valid == len(T)
            entry = self.model.update(packet.p_W if whole else packet.p_W[valid],
                                      packet.beam_dir_W if whole else packet.beam_dir_W[valid])
            # only what the model took in: a floater the gate turned away must not count as
            # retina measured deep inside the model (it would become every nearby point's margin)
            self.coverage.add(self.model.last_accepted)
            self.update_us.append(1e6 * (time.perf_counter() - t0) / n_valid)
            if self.logger is not None:
                self._log_model(entry)
        # the state is what this system last wrote (or the initial snapshot): kept at hand
        health = self.health
        if entry is not None or self._written.shape is None:
            self._written = snapshot_of(self.model, self.coverage, self._last_t, *self._trust,
                                        bound=self._bound)._replace(
                healthy_t_s=health.healthy_t_s, stream=health.why)
            if self.on_snapshot is not None:  # an observer's time is not the model's (wall_s)
                t0 = time.perf_counter()
                self.on_snapshot(self._written)
                self.observer_wall_s += time.perf_counter() - t0
        else:
            self._written = self._written._replace(t_s=self._last_t)
        state.get_mutable_abstract_state(0).set_value(self._written)
        self._mark_epoch(self._written)


