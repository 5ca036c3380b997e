"""The simulated iiOCT sensor on the robot: beam from the TRUE sensor pose, point from the
REPORTED joint angles and the CALIBRATED sensor pose, and its Drake block.

The A-scan is made where the fiber really looks: the scenario's true sensor frame
S_true (the nominal frame S with the calibration error the paper's plate calibration
leaves, planning.scenario) on the ground-truth eye. The retinal point the model receives
is reconstructed the way the real system does it: the extracted distance along the beam
of the calibrated sensor frame (by default the nominal S) at the joint angles the robot
reports (encoder noise, and optionally the OCT stream's time offset). So calibration,
encoder and synchronisation errors all reach the model, as in the paper.

Two modes:
- "ascan": synthesise the A-scan (models.iioct) and extract the distance: the full chain;
- "distance": draw the extracted distance from the extractor's error model (bias, SD and
  invalid probability as functions of distance and incidence, tabulated once per process
  by running the full chain; see `ExtractorErrorModel`): what the 1 kHz closed loop uses.

Units: mm, s, rad; frame W.
"""
from __future__ import annotations

from bisect import bisect_left
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import LeafSystem

from models.iioct import DistanceExtractor, Floater, OctEngine, synthesize_ascan
from planning.robot import Robot

DEFAULT_MAX_INCIDENCE_RAD = np.radians(55.0)


@dataclass(frozen=True, eq=False)
class SensorSample:
    """One iiOCT sample: OCT time stamp `t_s`; extracted `distance_mm` (NaN when
    invalid); `valid`, `confidence`, `reason` ("" when valid, else a models.iioct
    REASONS entry, "incidence", "no_retina" or "bad_joint_state"); the reconstructed
    retinal point `p_W` (NaN when invalid); the reported (calibrated) beam
    `beam_origin_W`, `beam_dir_W`; the raw `ascan` (None in "distance" mode); the true
    distance along the true beam (what evaluation compares with; nothing in the loop
    reads it)."""

    t_s: float
    distance_mm: float
    valid: bool
    confidence: float
    reason: str
    p_W: np.ndarray
    beam_origin_W: np.ndarray
    beam_dir_W: np.ndarray
    ascan: np.ndarray | None = None
    true_distance_mm: float = float("nan")  # simulation ground truth, for evaluation only

    def __deepcopy__(self, memo) -> SensorSample:
        return self  # immutable by contract: Drake copies abstract state values often


@dataclass(frozen=True)
class ExtractorErrorModel:
    """The extractor's error (extracted - true, mm) as a function of the true distance
    (mm) and the incidence (rad): `bias`, `sd` and `p_invalid` on the grid
    `distances_mm` x `incidences_rad`, interpolated bilinearly (clamped at the grid's
    edges). Errors are drawn Gaussian with that bias and SD."""

    distances_mm: tuple
    incidences_rad: tuple
    bias: list
    sd: list
    p_invalid: list

    def _interp(self, table: np.ndarray, d: float, a: float) -> float:
        D, A = self.distances_mm, self.incidences_rad
        i = min(max(bisect_left(D, d) - 1, 0), len(D) - 2)  # scalar code: called at 2 kHz
        j = min(max(bisect_left(A, a) - 1, 0), len(A) - 2)
        u = min(max((d - D[i]) / (D[i + 1] - D[i]), 0.0), 1.0)
        v = min(max((a - A[j]) / (A[j + 1] - A[j]), 0.0), 1.0)
        return float((1 - u) * (1 - v) * table[i][j] + u * (1 - v) * table[i + 1][j]
                     + (1 - u) * v * table[i][j + 1] + u * v * table[i + 1][j + 1])

    def draw(self, distance_mm: float, incidence_rad: float, rng: np.random.Generator) -> tuple[float, bool]:
        """(extracted distance mm, valid) for a true distance and incidence."""
        if rng.random() < self._interp(self.p_invalid, distance_mm, incidence_rad):
            return float("nan"), False
        mu = self._interp(self.bias, distance_mm, incidence_rad)
        sd = self._interp(self.sd, distance_mm, incidence_rad)
        return distance_mm + mu + sd * rng.standard_normal(), True


@lru_cache(maxsize=4)
def extractor_error_model(engine: OctEngine = OctEngine(), samples: int = 24, seed: int = 0) -> ExtractorErrorModel:
    """Tabulate the extractor's bias, SD (robust: 1.4826 x MAD) and invalid fraction over
    distances 0.5-25 mm and incidences 0-75 deg with `samples` A-scans per cell (about
    1 s; cached per process)."""
    rng = np.random.default_rng(seed)
    extractor = DistanceExtractor(engine)
    D = np.array([0.5, 1.0, 2.0, 4.0, 8.0, 14.0, 20.0, 25.0])
    A = np.radians([0.0, 20.0, 40.0, 55.0, 65.0, 75.0])
    bias, sd, p_invalid = (np.zeros((len(D), len(A))) for _ in range(3))
    for i, d in enumerate(D):
        for j, a in enumerate(A):
            m = [extractor(synthesize_ascan(d, a, rng, engine=engine)) for _ in range(samples)]
            err = np.array([x.distance_mm - d for x in m if x.valid])
            p_invalid[i, j] = 1.0 - len(err) / samples
            if len(err):
                med = float(np.median(err))
                bias[i, j], sd[i, j] = med, 1.4826 * float(np.median(np.abs(err - med)))
    return ExtractorErrorModel(tuple(D), tuple(A), bias.tolist(), sd.tolist(), p_invalid.tolist())


def _joint_rows(Q, m: int) -> np.ndarray:
    """Q as an (m, 6) float array of joint angles (rad): a row that is not 6 numbers, or
    an array of another shape, becomes a NaN row (reported per sample as a bad joint state)."""
    try:
        A = np.asarray(Q, dtype=float)
    except (TypeError, ValueError):  # ragged rows
        A = np.array([np.asarray(q, dtype=float) if np.shape(q) == (6,) else np.full(6, np.nan) for q in Q])
    return A if A.shape == (m, 6) else np.full((m, 6), np.nan)


class IioctSensor:
    """The iiOCT sensor on `robot` (planning.Robot built with a scenario).

    `mode`: "ascan" or "distance" (module docstring); `X_S_Scal`: (R, p mm) of the
    calibrated sensor frame in the nominal S (default identity: the calibrated pose is the
    nominal one, and the true one differs by the scenario's calibration error);
    `encoder_noise_rad`: SD of the noise on the reported joint angles; `max_incidence_rad`:
    samples whose beam meets the CURRENT MODEL (if `sample` gets one) more obliquely are
    rejected ("incidence": the extractor gives wrong-but-confident distances there);
    `engine`/`extractor`: models.iioct objects; `floater_rate`: fraction of samples with
    a vitreous floater on the beam (in "ascan" mode a Floater of 35-55 dB (the retina: 45 dB) at a random
    depth, which the extractor mostly rejects; in "distance" mode the worst case: a
    confident wrong distance, uniform between 0.5 mm and the retina); `seed`: speckle,
    noise and error draws.
    """

    def __init__(self, robot: Robot, *, mode: str = "ascan", X_S_Scal=None, engine: OctEngine | None = None,
                 extractor: DistanceExtractor | None = None, encoder_noise_rad: float = 0.0,
                 max_incidence_rad: float = DEFAULT_MAX_INCIDENCE_RAD, floater_rate: float = 0.0, seed: int = 0):
        if robot.scenario is None:
            raise ValueError("IioctSensor needs a Robot built with a scenario (the ground-truth eye)")
        if mode not in ("ascan", "distance"):
            raise ValueError(f"mode must be 'ascan' or 'distance', got {mode!r}")
        if not (np.isfinite(encoder_noise_rad) and encoder_noise_rad >= 0):
            raise ValueError(f"encoder_noise_rad must be >= 0 rad, got {encoder_noise_rad}")
        if not (np.isfinite(floater_rate) and 0.0 <= floater_rate <= 0.5):
            raise ValueError(f"floater_rate must be in [0, 0.5], got {floater_rate}")
        if not (0 < max_incidence_rad <= np.pi / 2):
            raise ValueError(f"max_incidence_rad must be in (0, pi/2] rad, got {max_incidence_rad}")
        self.robot, self.mode = robot, mode
        self.eye = robot.scenario.eye
        self.engine = OctEngine() if engine is None else engine
        self.extractor = DistanceExtractor(self.engine) if extractor is None else extractor
        self.error_model = extractor_error_model(self.engine) if mode == "distance" else None
        R, p = (np.eye(3), np.zeros(3)) if X_S_Scal is None else X_S_Scal
        self._R_S_Scal, self._p_S_Scal = np.asarray(R, dtype=float), np.asarray(p, dtype=float)
        self.encoder_noise_rad = float(encoder_noise_rad)
        self.max_incidence_rad = float(max_incidence_rad)
        self.floater_rate = float(floater_rate)
        self._rng = np.random.default_rng(seed)
        self.max_distance_mm = self.engine.depth_mm / self.engine.group_index - self.engine.tip_offset_mm

    def reported_beams(self, Q_reported: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(origins (M, 3) mm, unit directions (M, 3)) of the calibrated beam at the reported
        joint angles Q_reported (M, 6) rad (plus the encoder noise, drawn per sample)."""
        Q = Q_reported
        if self.encoder_noise_rad > 0:
            Q = Q + self.encoder_noise_rad * np.array([self._rng.standard_normal(6) for _ in range(len(Q))]).reshape(-1, 6)
        R_WS, p_WS = self.robot.poses("S", Q)
        return p_WS + R_WS @ self._p_S_Scal, R_WS @ self._R_S_Scal[:, 2]

    def true_geometry(self, Q_true) -> tuple[np.ndarray, np.ndarray]:
        """((M,) true distances mm along the true beams at Q_true (M, 6) to the retina,
        NaN where there is none; (M,) incidences rad)."""
        R, O = self.robot.poses("S_true", Q_true)
        U = R[:, :, 2]
        d = np.asarray(self.eye.ray_cast(O, U), dtype=float)
        d = np.where(np.isfinite(d) & (d > 0), d, np.nan)
        hit = np.isfinite(d)
        incidence = np.full(len(d), np.nan)
        if hit.any():
            N = self.eye.surface_normal(O[hit] + d[hit, None] * U[hit])
            incidence[hit] = np.arccos(np.minimum(1.0, np.abs(np.einsum("ij,ij->i", N, U[hit]))))
        return d, incidence

    def sample(self, q_true, q_reported, t_s: float, model=None) -> SensorSample:
        """One sample at OCT time t_s: the A-scan from the true pose at q_true, the point
        from q_reported (both (6,) rad). `model`: the current eye model (Sphere, Ellipsoid
        or anything with ray_cast and gradient in W) for the incidence check, or None."""
        return self.samples([q_true], [q_reported], [t_s], model)[0]

    def samples(self, Q_true, Q_reported, T_s, model=None) -> list[SensorSample]:
        """`sample` for M samples at once (Q_true, Q_reported (M, 6) rad; T_s (M,) s): the
        geometry is computed vectorised, which is what makes 2 kHz affordable."""
        nan3 = np.full(3, np.nan)
        out: list = [None] * len(T_s)
        Qt, Qr = _joint_rows(Q_true, len(T_s)), _joint_rows(Q_reported, len(T_s))
        finite = np.isfinite(Qt).all(axis=1) & np.isfinite(Qr).all(axis=1)
        good = np.flatnonzero(finite)
        for k in np.flatnonzero(~finite).tolist():
            out[k] = SensorSample(float(T_s[k]), float("nan"), False, 0.0,
                                  "bad_joint_state: q must be 6 finite angles (rad)", nan3, nan3, nan3)
        if not len(good):
            return out
        O, U = self.reported_beams(Qr[good])
        d_true, incidence = self.true_geometry(Qt[good])
        for k, origin, u, d0, a in zip(good.tolist(), O, U, d_true.tolist(), incidence.tolist()):
            out[k] = self._sample_one(float(T_s[k]), origin, u, d0, a, model)
        return out

    def _sample_one(self, t_s: float, origin, u, d_true: float, incidence: float, model) -> SensorSample:
        nan3 = np.full(3, np.nan)
        invalid = lambda reason, c=0.0, a=None: SensorSample(t_s, float("nan"), False, c, reason, nan3, origin, u, a,  # noqa: E731
                                                             d_true)
        if not np.isfinite(d_true) or d_true > self.max_distance_mm:
            return invalid("no_retina")
        if model is not None and self._model_incidence(model, origin, u) > self.max_incidence_rad:
            return invalid("incidence")
        floater = self.floater_rate > 0 and d_true > 1.0 and self._rng.random() < self.floater_rate
        if self.mode == "distance":
            if floater:
                d, ok = float(self._rng.uniform(0.5, d_true - 0.5)), True
            else:
                d, ok = self.error_model.draw(d_true, incidence, self._rng)
            ascan, confidence, reason = None, (0.9 if ok else 0.0), ("" if ok else "low_confidence")
        else:
            floaters = (Floater(float(self._rng.uniform(0.5, d_true - 0.5)), float(self._rng.uniform(35.0, 55.0))),) if floater else ()
            ascan = synthesize_ascan(d_true, incidence, self._rng, engine=self.engine, floaters=floaters)
            m = self.extractor(ascan)
            d, ok, confidence, reason = m.distance_mm, m.valid, m.confidence, m.reason
        if not ok:
            return invalid(reason, confidence, ascan)
        return SensorSample(t_s, float(d), True, float(confidence), "", origin + d * u, origin, u, ascan, d_true)

    @staticmethod
    def _model_incidence(model, origin, u) -> float:
        d = float(np.asarray(model.ray_cast(origin[None], u[None]))[0])
        if not np.isfinite(d):
            return 0.0
        g = np.asarray(model.gradient((origin + d * u)[None]))[0]
        return float(np.arccos(min(1.0, abs(g @ u) / np.linalg.norm(g))))


@dataclass(frozen=True, eq=False)
class _SensorState:
    """The block's state: the latest packet of samples, the (t, q) recorded since, and the
    history kept for the time offset. Immutable: Drake copies state values often."""

    packet: tuple
    pending: tuple = ()
    history: tuple = ()

    def __deepcopy__(self, memo) -> _SensorState:
        return self


class IioctSensorSystem(LeafSystem):
    """The sensor as a Drake block, sampling at `rate_hz` (default 2 kHz).

    Input "q" (6,) rad: the robot's joint angles. The OCT engine streams its A-scans in
    packets of `packet` samples (default 10, i.e. 5 ms at 2 kHz): the joint angles are
    recorded at every sample time and the packet is processed when complete (vectorised
    geometry). Outputs: "samples" (the latest packet, a tuple of SensorSample), "sample"
    (its last sample), "p_W" (3,) mm of that sample (NaN when invalid), "measurement"
    (4,) [distance_mm, valid 0/1, confidence, t_s] (t_s = -inf before the first packet).
    With `time_offset_s` > 0 the points are reconstructed from the joint angles of
    `time_offset_s` earlier (the paper's OCT-robot synchronisation error, up to 2.6 ms),
    interpolated linearly in the recorded history.
    """

    def __init__(self, sensor: IioctSensor, rate_hz: float = 2000.0, time_offset_s: float = 0.0, packet: int = 10):
        super().__init__()
        if not (np.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz must be > 0 Hz, got {rate_hz}")
        if not (np.isfinite(time_offset_s) and 0 <= time_offset_s <= 0.1):
            raise ValueError(f"time_offset_s must be in [0, 0.1] s, got {time_offset_s}")
        if not (isinstance(packet, int) and 1 <= packet <= 1000):
            raise ValueError(f"packet must be an int in [1, 1000] samples, got {packet}")
        self.sensor, self.rate_hz, self.time_offset_s, self.packet = sensor, float(rate_hz), float(time_offset_s), packet
        self._keep = int(np.ceil(time_offset_s * rate_hz)) + 1  # history samples kept from the last packet
        self._q = self.DeclareVectorInputPort("q", 6)
        nan3 = np.full(3, np.nan)
        first = SensorSample(-np.inf, np.nan, False, 0.0, "no_sample_yet", nan3, nan3, nan3)
        # state: (latest packet of samples, recorded (t, q) not yet processed, history kept for the offset)
        self._state = self.DeclareAbstractState(AbstractValue.Make(_SensorState((first,))))
        self.DeclarePeriodicUnrestrictedUpdateEvent(1.0 / rate_hz, 0.0, self._update)
        self.DeclareAbstractOutputPort("samples", lambda: AbstractValue.Make((first,)), self._calc_samples)
        self.DeclareAbstractOutputPort("sample", lambda: AbstractValue.Make(first), self._calc_sample)
        self.DeclareVectorOutputPort("p_W", 3, self._calc_p)
        self.DeclareVectorOutputPort("measurement", 4, self._calc_measurement)

    def _reported(self, T: np.ndarray, Q: np.ndarray, history: tuple) -> np.ndarray:
        """Joint angles (M, 6) at T - time_offset_s, from the recorded (t, q) so far."""
        if self.time_offset_s == 0.0:
            return Q
        ts = np.concatenate([[h[0] for h in history], T])
        Qs = np.vstack([np.array([h[1] for h in history]).reshape(-1, 6), Q])
        return np.column_stack([np.interp(T - self.time_offset_s, ts, Qs[:, i]) for i in range(6)])

    def _update(self, context, state) -> None:
        st = context.get_abstract_state(0).get_value()
        packet, history = st.packet, st.history
        pending = st.pending + ((context.get_time(), np.array(self._q.Eval(context))),)
        if len(pending) >= self.packet:
            T = np.array([p[0] for p in pending])
            Q = np.array([p[1] for p in pending])
            packet = tuple(self.sensor.samples(Q, self._reported(T, Q, history), T))
            history = (history + pending)[-self._keep:] if self.time_offset_s > 0 else ()
            pending = ()
        state.get_mutable_abstract_state(0).set_value(_SensorState(packet, pending, history))

    def _latest(self, context) -> SensorSample:
        return context.get_abstract_state(0).get_value().packet[-1]

    def _calc_samples(self, context, value) -> None:
        value.set_value(context.get_abstract_state(0).get_value().packet)

    def _calc_sample(self, context, value) -> None:
        value.set_value(self._latest(context))

    def _calc_p(self, context, output) -> None:
        output.SetFromVector(self._latest(context).p_W)

    def _calc_measurement(self, context, output) -> None:
        s = self._latest(context)
        output.SetFromVector([s.distance_mm, float(s.valid), s.confidence, s.t_s])
