"""The local retina model: a radial height field over directions from a fixed centre,
fitted online from the measured retinal points on top of the adaptive model's global
quadric, with a standard deviation (mm) at every direction.

Representation (chosen by measurement on the closed loop's spiral, six shapes, sensor
seed 0, against the true retina within 10 deg of a measured direction; the figures are
in the README's results): nodes on a Fibonacci sphere about `spacing_deg` apart; each
node holds the weighted least-squares normal equations of a quadratic radius r(t1, t2)
in gnomonic coordinates about its direction, the weights Wendland's C2 function of the
angle over `support_deg` (moving least squares: Lancaster & Salkauskas 1981; Wendland,
Adv. Comput. Math. 4, 1995, for the compactly supported weight). A point touches only
the nodes within the support (a few dozen): O(1) per A-scan, exact information-form
accumulation, each A-scan weighted by its share of a sample (`sample_length_mm`: dense
A-scans along one scan line are not independent evidence). Each node's solution adds the global quadric's Taylor expansion there as
a Gaussian prior (its value uncertain by the global model's standard deviation, which
grows with the angle from the measured directions), so a node with little data falls
back to the global model and one with much data follows the retina. The field at a
direction blends the nearby nodes' quadratics with Wendland weights over `blend_deg`
(a partition of unity: smooth, and exact where the quadratics agree).

Why this and not a global basis: spherical harmonics or a global RBF solve couple every
coefficient (a dense solve per update, or a rank-1 update of a K x K inverse: K^2 per
A-scan, ~4 ms at K = 2,000); a Gaussian process needs its neighbours' Cholesky per
query (tens of us per point at 1 kHz x ten points). The node-local normal equations
cost about 50 x 27 multiply-adds per point and a few 6 x 6 Cholesky solves per update.

The global quadric under it (models.adaptive.model.AdaptiveEyeModel.global_for_local): the
ellipsoid once the transition criteria accept it, else the robust ellipsoid
(models.fit.streaming_robust: Tukey's biweight leaves a detachment or a staphyloma out of
the fit) while it is an eye's and predicts the new points better than the sphere (once
taken, over a longer run of them: AdaptiveEyeModel._globe_taken); else, while the
criteria's ellipsoid is no eye's (the pointed eye's cigar), the eye globe
(models.fit.eye_globe: the eye's ellipsoid nearest the points and the trocar), with the
sphere's standard deviations; else the sphere. Measured
on the closed loop's spiral (sensor seed 11): on the detached eye the sphere under the
local model left 881 um of mean error more than 10 deg from the data and the robust
ellipsoid 59 um; on the staphyloma 445 and 82 um (the figures in the README's results).

Uncertainty: a node's standard deviation is its posterior's (noise `noise_mm`), scaled
by the Birge ratio (weighted mean square residual over the noise's, when larger) and
increased by the residual's excess over the noise (a quadratic that cannot follow the
retina within its support says so) and by its quadratic's largest error at the data
nodes within `blend_deg` (its extrapolation's error where the data show it: at the rim
of a detachment a quadratic from one side misses the other side); nodes without data
take the global model's standard deviation, `sd_near_mm` next to measured directions
growing linearly to `sd_far_mm` at `far_deg` from them and beyond, and the departure of
the retina from the global quadric at the data nodes within `departure_deg` (tapered
linearly to 0 there: a pathology may go on past the data's edge as far as the data show
it departing). The same departures set the prior of every node's offset and tilt, data
nodes' included, and a node's own departure its curvature's (kernels.solve_node): a node
on a detachment's flank, fitted from data several degrees off, is not held to a global
quadric the data nearby show to be off by a millimetre (measured on the loop's spiral,
seed 0: with the global model's standard deviation alone in the prior, 0.85 % of the
detached eye's reference samples had the model's retina beyond the true one by more
than 3 sigma, up to 8 sigma and 0.60 mm, 2-10 deg from the data; with the departures,
none, in the 1,000-scenario campaign's model as in the seed-11 runs). Last, the standard
deviation is calibrated on the model's own held-out predictions (models.local.calibration:
each point predicted before it is absorbed), a factor per angle from the data that makes
99 % of those errors lie within 3 sigma. The field blends the nodes' standard deviations and adds the spread of
their radii about the blended one (the variance of a mixture: where the nodes disagree,
none of them is to be trusted). Measured on the same spiral: the error within 1 deg of
the data has p95 27-29 um; it grows to 350-870 um at 4-10 deg from it over the
detachment and the staphyloma, beyond the scan lines' ends (the quadratics' bias between
lines 4-10 deg apart and their extrapolation past the edge of the data, not the noise),
and the standard deviation with it: 3 sigma covers 99.3-100 % of the reference region
(100 % on the six shapes and four variants in the closed loop's own runs, seed 11: the
README's table).
The support is 12 deg: on the loop's spiral (seed 0) a 9 deg quadratic bends between
scan lines that cross a 3 mm staphyloma's wall several degrees apart (scanned p95 111 um;
12 deg: 39 um). Nodes 9-12 deg into a detachment's unscanned top then hold faint data and
take the no-data departure rule too (departures.FAINT_SUPPORT).
Units: mm, rad (deg where named).
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from models.adaptive.coverage import fibonacci_directions
from models.local.field import LocalField, bound_params
from models.local.calibration import SigmaCalibration
from models.local.config import LocalConfig
from models.local.field_kernels import BOUND_SIZE, radii_at
from models.local.departures import FAINT_SUPPORT, fill_trend, neighbour_table, node_departures, spread_departures
from models.local.geometry import ELLIPSOID, GLOBAL_SIZE, N_BASIS, N_COV, node_frames
from models.local.kernels import global_params, solve_nodes
from models.local.online import holds, local_step
from models.shapes.validation import as_beams, as_points, as_vector3


_NO_GLOBAL = np.zeros(GLOBAL_SIZE)
_NO_BEAMS = np.zeros((0, 3))


def sweep_share(credit: float, rate: float, n_points: int) -> tuple[int, float]:
    """(nodes, credit): the sweep's re-solves for an update of n_points points at `rate`
    per point, with `credit` (< 1) owed from the updates before: over any split of a stream
    into updates, floor(rate x its points) in all (a 1e-9 tolerance: five updates of one
    point at 0.2 owe one node however the sum rounds)."""
    credit += rate * n_points
    nodes = int(credit + 1e-9)
    return nodes, max(credit - nodes, 0.0)


@lru_cache(maxsize=4)
def _neighbour_table_of(n: int, reach_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """departures.neighbour_table of the n-node grid, once per process (read-only: shared)."""
    table = neighbour_table(fibonacci_directions(n), np.radians(reach_deg))
    for a in table:
        a.setflags(write=False)
    return table


@lru_cache(maxsize=4)
def _node_frames_of(n: int) -> np.ndarray:
    """geometry.node_frames of the n-node grid, once per process (read-only: shared)."""
    frames = node_frames(fibonacci_directions(n))
    frames.setflags(write=False)
    return frames


class LocalRetinaModel:
    """The online local model about the fixed centre `center` (3,) mm (the nominal eye
    centre; every direction is seen from it). `update(P, shape, trend)` absorbs points P (N, 3)
    mm (non-finite rows skipped) with `shape` the current global Sphere or Ellipsoid
    (None, or one that does not hold the centre: the last one that did; the nodes are
    solved once there is one); `field()` the
    current LocalField (models.local.field); `radius_and_sd(U)` the blended radius and
    standard deviation (mm) along unit directions U (M, 3)."""

    def __init__(self, center, config: LocalConfig | None = None):
        self.config = LocalConfig() if config is None else config
        self.center = as_vector3(center, "center").copy()
        cfg = self.config
        n = int(np.ceil(4.0 * np.pi / np.radians(cfg.spacing_deg) ** 2))
        self.n_nodes = n
        self._dirs = fibonacci_directions(n)
        self._A = np.zeros((n, N_BASIS, N_BASIS))
        self._b = np.zeros((n, N_BASIS))
        self._rr = np.zeros(n)
        self._wsum = np.zeros(n)
        self._near = np.full(n, -1.0)  # cosine of the nearest data angle
        self._listed = np.zeros(n, dtype=np.bool_)
        self._dirty = np.zeros(n, dtype=np.int64)
        self._n_dirty = 0
        self._x = np.zeros((n, N_BASIS))
        self._cov = np.zeros((n, N_COV))
        self._excess = np.zeros(n)
        self._extra = np.zeros(n)  # the variance the field adds per node: excess and the departures (_spread)
        self._dev = np.zeros(n)  # each node's data's departure from the global quadric at its last solve (mm)
        self._slope = np.zeros((n, 2))  # and its slope (mm/rad, in the node's frame)
        self._has = np.zeros(n)
        self._data_nodes = np.zeros(n, dtype=np.int64)  # nodes with data, in the order they got it
        self._n_data = 0
        self._solved_w = np.zeros(n)
        self._in_data = np.zeros(n, dtype=np.bool_)
        self._sweep_at = 0
        self._sweep_credit = 0.0  # re-solves owed to the sweep (sweep_per_point per point given)
        self._last = np.zeros(5)  # the last taken point's position (3,), whether there is one; n_samples
        self._gp = None
        self._priors = (cfg.prior_for(False), cfg.prior_for(True))
        self._prior = self._priors[0]
        self._far_prior = None  # _prior_of's last raised prior
        self._shape_seen, self._shape_gp = None, None
        self._trend_seen, self._tp = None, _NO_GLOBAL
        self._support, self._track, self._blend = (np.radians(cfg.support_deg), np.radians(cfg.track_deg),
                                                   np.radians(cfg.blend_deg))
        self._reach = np.radians(cfg.departure_deg)
        self.n_points = 0
        self._updates = 0
        self._field, self._field_key, self._field_at = None, None, 0
        self._bound, self._bound_key = None, None  # field's last bound and its block (field)
        self._gate = np.array([cfg.min_radius_mm, cfg.max_radius_mm, cfg.gate_mm])
        self.calibration = SigmaCalibration()
        self.last_predictions = np.empty((0, 6))

    @property
    def global_params(self) -> np.ndarray | None:
        """The kernels' packing of the global quadric of the last update (None before one)."""
        return self._gp

    @property
    def n_samples(self) -> float:
        """The samples the taken points count as: their shares (LocalConfig.sample_length_mm)
        summed, the scan lines' length on the retina over sample_length_mm."""
        return float(self._last[4])

    @property
    def dirs(self) -> np.ndarray:
        """(n, 3) the nodes' directions (read, don't change)."""
        return self._dirs

    def update(self, P, shape=None, trend=None, shape_sd_mm=None, beam_W=None) -> None:
        """Absorb the points P (N, 3) mm; `beam_W`: None or their beams' directions (N, 3),
        which measure each A-scan's share of a sample across its beam, where its noise does
        not lengthen it (models.local.kernels.absorb_points). Re-solve the nodes they
        touched (up to solves_per_point x N, the rest at the next updates: consecutive A-scans touch mostly
        the same nodes) and sweep_per_point x N more nodes with data in turn (the global prior moves
        with every update of the global fit). Each point is first predicted by the model as
        it stood (last_predictions) and the sd's calibration takes the errors. `trend`: None
        or the Ellipsoid the nodes read past the data and are centred on (LocalConfig.trend_deg;
        one that does not hold the centre 1 mm deep: none). `shape_sd_mm`: None, or the
        global quadric's own sd far from the data (mm), where it exceeds the config's for its
        kind (up to the sphere's sd_far_mm); math.inf: a quadric no better known than the
        sphere fit (the eye globe, models.fit.eye_globe), which takes the sphere's prior. One compiled call (models.local.online.local_step)."""
        if not (type(P) is np.ndarray and P.dtype == np.float64 and P.ndim == 2 and P.flags.c_contiguous):
            P = np.ascontiguousarray(as_points(P, "P", allow_nonfinite=True).reshape(-1, 3))
        B = _NO_BEAMS if beam_W is None else as_beams(beam_W, len(P))
        self._updates += 1
        gp = self._global_of(shape)
        if trend is not self._trend_seen:
            tp = _NO_GLOBAL if trend is None else global_params(trend)
            self._trend_seen, self._tp = trend, tp if trend is not None and holds(tp, self.center, 1.0) else _NO_GLOBAL
        old = _NO_GLOBAL if self._gp is None else self._gp
        prior = self._prior if gp is None else self._prior_of(gp, shape_sd_mm)
        cfg, cal = self.config, self.calibration
        pred = np.empty((len(P), 6))
        sweep, self._sweep_credit = (0, self._sweep_credit) if gp is None else sweep_share(  # owed once there is a global model
            self._sweep_credit, cfg.sweep_per_point, len(P))
        self._n_dirty, taken, self._n_data, self._sweep_at = local_step(
            P, B, self.center, old, self._prior, _NO_GLOBAL if gp is None else gp, prior, self._tp, self._gate,
            self._dirs,
            self._support, self._track, self._blend, cfg.relist_growth, max(len(P), 1) * cfg.solves_per_point,
            sweep, self._reach, *self._neighbours(), self._A, self._b, self._rr, self._wsum, self._near,
            self._listed, self._dirty, self._n_dirty, self._solved_w, self._data_nodes, self._n_data, self._in_data,
            self._sweep_at, self._x, self._cov, self._excess, self._extra, self._has, self._dev, self._slope, cal.k,
            cal.width, cal.hist, cal.count, cal.memory, pred, self._last, cfg.sample_length_mm)
        self.n_points += taken
        self.last_predictions = pred
        if gp is not None:
            self._gp, self._prior = gp, prior

    def _prior_of(self, gp: np.ndarray, shape_sd_mm) -> np.ndarray:
        """The kernels' prior on the global quadric gp: its kind's (prior_for), its sd far from
        the data raised to shape_sd_mm (at most sd_far_mm), reached at the kind's rate per
        angle from the data: within far_deg of the data the sd is the kind's, as the held-back
        spirals of the faults campaign need (raised there at once, the detached eye's and the
        staphyloma's lag builds scanned 31 % and 29 % of the region against 41 % and 39 %),
        and the nodes no data came within track_deg of (angle pi) take the quadric's own, up
        to the kind's rate x 180 deg (1.55 mm on an ellipsoid). The same array while it is
        the same."""
        if shape_sd_mm == math.inf:  # a global quadric no better known than the sphere fit
            return self._priors[0]
        base = self._priors[int(gp[0] == ELLIPSOID)]
        if shape_sd_mm is None or not shape_sd_mm > base[2]:
            return base
        far = min(float(shape_sd_mm), self.config.sd_far_mm)
        if self._far_prior is None or self._far_prior[2] != far or self._far_prior[1] != base[1]:
            self._far_prior = base.copy()
            self._far_prior[2] = far
            self._far_prior[3] = base[3] * (far - base[1]) / (base[2] - base[1])
        return self._far_prior

    def _global_of(self, shape) -> np.ndarray | None:
        """The kernels' packing of the Sphere or Ellipsoid `shape`, or, when it is None or
        does not hold the centre at least 1 mm deep, the last one that did (None before
        one; the same shape object is packed once). Radii about the centre are defined only
        for a quadric that holds it: an early fit through a few points of a small patch
        need not."""
        if shape is None:
            return self._gp
        if shape is not self._shape_seen:
            g = global_params(shape)
            self._shape_seen, self._shape_gp = shape, g if holds(g, self.center, 1.0) else None
        return self._gp if self._shape_gp is None else self._shape_gp

    def solve_all(self) -> None:
        """Solve every node with data at once (a snapshot for evaluation; the online path
        spreads this over updates)."""
        if self._gp is None or not self._n_data:
            return
        nodes = self._data_nodes[:self._n_data].copy()
        # every node's departure first (order-free: a node's solve reads its neighbours')
        node_departures(nodes, self._dirs, self.center, self._gp, self._A, self._b, self._wsum, self._dev)
        self._has[nodes] = 1.0
        solve_nodes(nodes, len(nodes), self._dirs, self.center, self._gp, self._tp, self._A, self._b, self._rr, self._wsum,
                    self._near, self._prior, self._reach, *self._neighbours(), self._dev, self._slope, self._x, self._cov,
                    self._excess, self._has, self._listed, self._solved_w)
        self._n_dirty = 0

    def _neighbours(self, reach_deg: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The grid's neighbour table within reach_deg (default departure_deg; shared by every
        model of the process, never copied with one: ~16 MB at 25 deg)."""
        return _neighbour_table_of(self.n_nodes, self.config.departure_deg if reach_deg is None else reach_deg)

    def _spread(self) -> None:
        """The nodes without data take the departure of the data nodes near them
        (departures.spread_departures) and, within trend_deg of the data, the trend's
        quadratic (departures.fill_trend): with each field (params, radius_and_sd); the
        predictions of the updates between read the last ones."""
        spread_departures(self._dirs, _node_frames_of(self.n_nodes), self._x, self._has, self._excess, self._dev,
                          self._slope, self._near, np.radians(self.config.spacing_deg), FAINT_SUPPORT * self._support,
                          self._reach, self.config.departure_floor_mm, self._blend, *self._neighbours(),
                          *self._neighbours(self.config.blend_deg), self._extra)
        fill_trend(self._dirs, self._has, self._near, self.center, self._tp, np.cos(np.radians(self.config.trend_deg)),
                   self._x)

    def radius_and_sd(self, U) -> tuple[np.ndarray, np.ndarray]:
        """((M,) radius mm, (M,) sd mm) along the unit directions U (M, 3) from the centre."""
        U = np.ascontiguousarray(np.asarray(U, dtype=float).reshape(-1, 3))
        if self._gp is None:
            return np.full(len(U), np.nan), np.full(len(U), np.inf)
        self._spread()
        return radii_at(self._dirs, self._blend, 1.0, self.center, self._prior, self._gp, self.calibration.factors,
                        self._x, self._cov, self._extra, self._has, self._near, U)

    def field(self, local: bool = True, kind: str = "local", bound=None):
        """The LocalField (models.local.field) of params(local, bound), remade at most every
        `refresh` updates (a copy of the nodes, ~1 MB): a snapshot up to that many sensor
        packets old, unless `local`, the kind or the bound changed. It answers the model
        alone; `bound` (sigma_factor, fallback Sphere, keep_mm) writes the barrier's bound into its
        params, so that its with_fallback of that bound shares them."""
        if bound is not self._bound:  # the bound's block, made once per bound object (the loop's never changes)
            self._bound, self._bound_key = bound, None if bound is None else tuple(bound_params(*bound))
        key = (local, kind, self._bound_key)
        if self._field is None or self._field_key != key or self._updates - self._field_at >= self.config.refresh:
            self._field = LocalField(self.params(local, bound), kind)
            self._field_key, self._field_at = key, self._updates
        return self._field

    def params(self, local: bool = True, bound=None) -> np.ndarray:
        """The LocalField params: the current nodes on the current global model; `local`
        False: the global surface with the local estimate's disagreement in its sd; `bound`
        (sigma_factor, fallback Sphere, keep_mm) or None: the barrier's bound block (bound_params)."""
        if self._gp is None:
            raise ValueError("LocalRetinaModel.params: no global model yet (update with a shape first)")
        self._spread()
        head = np.concatenate([[self.n_nodes, self._blend, 1.0 if local else 0.0], self.center, self._prior, self._gp,
                               self.calibration.factors, np.zeros(BOUND_SIZE) if bound is None else bound_params(*bound)])
        return np.ascontiguousarray(np.concatenate([head, self._dirs.ravel(), self._x.ravel(), self._cov.ravel(), self._extra,
                                                    self._has, self._near]))
