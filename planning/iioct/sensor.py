"""The simulated iiOCT sensor on the robot: beam from the TRUE sensor pose, point from the
REPORTED joint angles and the CALIBRATED sensor pose.

The A-scan is made where the fiber really looks: the scenario's true sensor frame
S_true (the nominal frame S with the calibration error the paper's plate calibration
leaves, planning.scenario) on the ground-truth eye. The retinal point the model receives
is reconstructed the way the real system does it: the extracted distance along the beam
of the calibrated sensor frame (by default the nominal S) at the joint angles the robot
reports (encoder noise, and optionally the OCT stream's time offset). So calibration,
encoder and synchronisation errors all reach the model, as in the paper.

Two modes, the same geometry (planning.iioct.kernels):
- "ascan": synthesise the A-scan (models.iioct) and extract the distance: the full chain;
- "distance": draw the extracted distance from the extractor's error model (bias, SD and
  invalid probability as functions of distance and incidence, tabulated once per process
  by running the full chain; see models.iioct.error_model): what the 1 kHz closed loop uses.

Units: mm, s, rad; frame W.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from models.iioct import DistanceExtractor, Floater, OctEngine, synthesize_ascan
from models.iioct.error_model import extractor_error_model
from models.shapes.rays import beam_incidences_rad
from planning.iioct.kernels import (DISTANCE_REASONS, NO_RETINA, all_finite, beam_points, distance_packet,
                                    packet_geometry, sensor_beams)
from planning.iioct.packet import BAD_JOINT_STATE, PER_SAMPLE_ARRAYS, SensorPacket, SensorSample, scattered
from planning.robot import Robot

DEFAULT_MAX_INCIDENCE_RAD = np.radians(55.0)
_NO_FLOATER_DRAWS = np.empty((2, 0))  # distance_packet's floater draws without floaters


class IioctSensor:
    """The iiOCT sensor on `robot` (planning.Robot built with a scenario).

    `mode`: "ascan" or "distance" (module docstring); `X_S_Scal`: (R, p mm) of the
    calibrated sensor frame in the nominal S (default identity: the calibrated pose is the
    nominal one, and the true one differs by the scenario's calibration error);
    `encoder_noise_rad`: SD of the noise on the reported joint angles; `max_incidence_rad`:
    samples whose beam meets the CURRENT MODEL (if `sample` gets one) more obliquely are
    rejected ("incidence": the extractor gives wrong-but-confident distances there; the
    closed loop's model system keeps the same limit, eval.systems.model);
    `engine`/`extractor`: models.iioct objects; `floater_rate`: fraction of samples with
    a vitreous floater on the beam (in "ascan" mode a Floater of 35-55 dB (the retina:
    45 dB) at a random depth, which the extractor mostly rejects; in "distance" mode the
    worst case: a confident wrong distance, uniform between 0.5 mm and the retina);
    `seed`: speckle, noise and error draws.

    `frames`: (S (6, n), R_true, p_true mm, R_cal, p_cal mm), the chain's screw axes and
    the true and calibrated sensor frames' home poses in W: the kernels' leading
    arguments (planning.iioct.kernels).
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
        chain = robot.chain
        R_S, p_S = chain.homes["S"]  # the calibrated frame's home pose: S's composed with X_S_Scal
        home_Scal = (np.ascontiguousarray(R_S @ np.asarray(R, dtype=float)), R_S @ np.asarray(p, dtype=float) + p_S)
        self.frames = (chain.S, *chain.homes["S_true"], *home_Scal)
        self.encoder_noise_rad = float(encoder_noise_rad)
        self.max_incidence_rad = float(max_incidence_rad)
        self.floater_rate = float(floater_rate)
        self._rng = np.random.default_rng(seed)
        self.max_distance_mm = self.engine.depth_mm / self.engine.group_index - self.engine.tip_offset_mm
        if mode == "distance":  # the packet's kernels loaded from numba's cache (compiled on a fresh
            # checkout) now, not inside the first packet of a timed closed-loop run; no draws taken
            q = np.zeros((1, 6))
            all_finite(q, q)
            self.distance_arrays(q, q, np.zeros(1), np.zeros(1), np.zeros((2, 1)))

    def reseed(self, seed) -> None:
        """Draw speckle, noise and errors from `seed` (an int or a numpy SeedSequence) from
        here on: a run seeded alone does not depend on the runs before it."""
        self._rng = np.random.default_rng(seed)

    def reported_beams(self, Q_reported) -> tuple[np.ndarray, np.ndarray]:
        """(origins (M, 3) mm, unit directions (M, 3)) in W of the calibrated beam at the
        reported joint angles Q_reported (M, 6) rad, finite (plus the encoder noise, drawn
        per sample)."""
        Q = self._with_encoder_noise(_finite_rows(Q_reported))
        return sensor_beams(*self.frames, Q, Q)[2:]

    def true_geometry(self, Q_true) -> tuple[np.ndarray, np.ndarray]:
        """((M,) true distances mm along the true beams at Q_true (M, 6) rad, finite, to
        the retina, NaN where there is none; (M,) incidences rad, NaN without a hit)."""
        Q = _finite_rows(Q_true)
        return self._geometry(Q, Q)[2:4]

    def _with_encoder_noise(self, Q: np.ndarray) -> np.ndarray:
        if self.encoder_noise_rad > 0:
            return Q + self.encoder_noise_rad * self._rng.standard_normal((len(Q), 6))
        return Q

    def _geometry(self, Q_true: np.ndarray, Q_reported: np.ndarray) -> tuple:
        """`packet_geometry` of this sensor at finite joint angles (M, 6) rad."""
        return packet_geometry(*self.frames, np.ascontiguousarray(Q_true), np.ascontiguousarray(Q_reported),
                               self.eye.hit_arguments, self.max_distance_mm)

    def sample(self, q_true, q_reported, t_s: float, model=None) -> SensorSample:
        """One sample at OCT time t_s: the A-scan from the true pose at q_true, the point
        from q_reported (both (6,) rad). `model`: the current eye model (Sphere, Ellipsoid
        or anything with ray_cast and gradient in W) for the incidence check, or None."""
        return self.samples([q_true], [q_reported], [t_s], model)[0]

    def samples(self, Q_true, Q_reported, T_s, model=None) -> list[SensorSample]:
        """`sample` for M samples at once (Q_true, Q_reported (M, 6) rad; T_s (M,) s): the
        SensorSamples of `packet`."""
        return self.packet(Q_true, Q_reported, T_s, model).samples()

    def packet(self, Q_true, Q_reported, T_s, model=None) -> SensorPacket:
        """The M samples at OCT times T_s (M,) s from the true joint angles Q_true and the
        reported ones Q_reported (M, 6) rad (`sample`'s, in order) as a SensorPacket: the
        geometry, the checks and (in "distance" mode) the error draws vectorised over the
        M samples, which is what makes 2 kHz affordable; in "distance" mode one compiled
        call (`distance_packet`) after the draws (and a compiled finiteness check before
        them). A row that is not 6 finite angles gives an invalid sample (reason
        BAD_JOINT_STATE) and draws nothing.

        Draws from the sensor's generator, in order: the encoder noise (M x 6 normals, if
        any); in "distance" mode M uniforms, M standard normals and, with floaters, 2 x M
        uniforms, sample m taking the m-th of each whether it has a retina or not (a
        sample without one, or rejected for its incidence on `model`, leaves its draws
        unused; every sample has the same error and floater statistics either way)."""
        M = len(T_s)
        return self.packet_of_arrays(np.array(T_s, dtype=float).reshape(M), _joint_rows(Q_true, M),
                                     _joint_rows(Q_reported, M), model)

    def packet_of_arrays(self, T: np.ndarray, Q_true: np.ndarray, Q_reported: np.ndarray, model=None) -> SensorPacket:
        """`packet` without its input conversions: the samples at times T (M,) s (a float
        array the packet keeps) from the joint angles Q_true, Q_reported, C-contiguous
        (M, 6) float arrays (rad), NaN rows for bad joint states."""
        if all_finite(Q_true, Q_reported):
            return self._measure(T, Q_true, Q_reported, model)
        M = len(T)
        good = np.flatnonzero(np.isfinite(Q_true).all(axis=1) & np.isfinite(Q_reported).all(axis=1))
        out = SensorPacket.invalid(T, BAD_JOINT_STATE)
        if not len(good):
            return out
        part = self._measure(T[good], Q_true[good], Q_reported[good], model)
        for name in PER_SAMPLE_ARRAYS:
            getattr(out, name)[good] = getattr(part, name)
        return out._replace(reasons=scattered(out.reasons, good, part.reasons),
                            ascans=None if part.ascans is None else scattered((None,) * M, good, part.ascans))

    def _measure(self, T: np.ndarray, Qt: np.ndarray, Qr: np.ndarray, model) -> SensorPacket:
        """The packet of the samples at times T (M,) s (the packet keeps T) from finite
        joint angles Qt, Qr (M, 6) rad, C-contiguous (the encoder noise drawn first)."""
        Qr = self._with_encoder_noise(Qr)
        if self.mode == "distance":
            return self._distance_packet(T, Qt, Qr, model)
        O, U, d_true, incidence, live = self._geometry(Qt, Qr)
        M = len(T)
        reasons = ["" if ok else "no_retina" for ok in live.tolist()]
        for k in self._oblique(model, O, U, live).tolist():
            live[k], reasons[k] = False, "incidence"
        d, valid, confidence = np.full(M, np.nan), np.zeros(M, dtype=bool), np.zeros(M)
        ascans = [None] * M
        for k in np.flatnonzero(live).tolist():
            ascans[k], m = self._ascan_one(float(d_true[k]), float(incidence[k]))
            d[k], valid[k], confidence[k], reasons[k] = m.distance_mm, m.valid, m.confidence, "" if m.valid else m.reason
        d[~valid] = np.nan
        return SensorPacket(T, d, valid, confidence, tuple(reasons), beam_points(O, U, d, valid), O, U, tuple(ascans),
                            d_true)

    def _distance_packet(self, T: np.ndarray, Qt: np.ndarray, Qr: np.ndarray, model) -> SensorPacket:
        """`_measure` in "distance" mode: `distance_packet` with M uniforms, M standard
        normals and, with floaters, 2 x M uniforms drawn in that order; a sample rejected
        for its incidence on `model` (if any) leaves its draws unused."""
        M, rng = len(T), self._rng
        uniform, normal = rng.random(M), rng.standard_normal(M)
        floater_draws = rng.random((2, M)) if self.floater_rate > 0 else _NO_FLOATER_DRAWS
        d, valid, confidence, codes, P, O, U, d_true = self.distance_arrays(Qt, Qr, uniform, normal, floater_draws)
        reasons = _distance_reasons(codes.tobytes())
        if model is not None:
            oblique = self._oblique(model, O, U, codes != NO_RETINA)
            d[oblique], valid[oblique], confidence[oblique], P[oblique] = np.nan, False, 0.0, np.nan
            reasons = scattered(reasons, oblique, ("incidence",) * len(oblique))
        return SensorPacket(T, d, valid, confidence, reasons, P, O, U, None, d_true)

    def distance_arrays(self, Q_true: np.ndarray, Q_reported: np.ndarray, uniform: np.ndarray, normal: np.ndarray,
                        floater_draws: np.ndarray) -> tuple:
        """`distance_packet` of this sensor's chain, eye, range and error model at the
        finite joint angles Q_true, Q_reported (M, 6) rad (C-contiguous) with the draws
        uniform, normal (M,) and floater_draws (2, M) (read only with floaters)."""
        return distance_packet(*self.frames, Q_true, Q_reported, self.eye.hit_arguments, self.max_distance_mm,
                               *self.error_model.grid, uniform, normal, self.floater_rate, floater_draws)

    def _oblique(self, model, O: np.ndarray, U: np.ndarray, live: np.ndarray) -> np.ndarray:
        """The indices of the `live` (M,) samples whose calibrated beams (origins O, unit
        directions U (M, 3) in W) meet `model` (anything with ray_cast and gradient in W,
        or None: none) more obliquely than max_incidence_rad."""
        if model is None or not live.any():
            return np.empty(0, dtype=int)
        return np.flatnonzero(live)[beam_incidences_rad(model, O[live], U[live]) > self.max_incidence_rad]

    def _ascan_one(self, d_true: float, incidence: float):
        """(A-scan, models.iioct extraction) of one sample with a retina at d_true mm and
        incidence rad in "ascan" mode, with a floater at the floater rate."""
        floater = self.floater_rate > 0 and d_true > 1.0 and self._rng.random() < self.floater_rate
        floaters = ((Floater(float(self._rng.uniform(0.5, d_true - 0.5)), float(self._rng.uniform(35.0, 55.0))),)
                    if floater else ())
        ascan = synthesize_ascan(d_true, incidence, self._rng, engine=self.engine, floaters=floaters)
        return ascan, self.extractor(ascan)


def _finite_rows(Q) -> np.ndarray:
    """Q as an (M, 6) float array of finite joint angles (rad); ValueError otherwise."""
    A = np.asarray(Q, dtype=float)
    if A.ndim != 2 or A.shape[1] != 6 or not np.all(np.isfinite(A)):
        raise ValueError(f"Q must be finite joint angles of shape (M, 6) in rad, got shape {A.shape}")
    return A


def _joint_rows(Q, m: int) -> np.ndarray:
    """Q as a C-contiguous (m, 6) float array of joint angles (rad): a row that is not 6
    numbers, or an array of another shape, becomes a NaN row (reported per sample as a bad
    joint state)."""
    try:
        A = np.ascontiguousarray(Q, dtype=float)
    except (TypeError, ValueError):  # ragged rows
        A = np.array([np.asarray(q, dtype=float) if np.shape(q) == (6,) else np.full(6, np.nan) for q in Q])
    return A if A.shape == (m, 6) else np.full((m, 6), np.nan)


@lru_cache(maxsize=4096)
def _distance_reasons(codes: bytes) -> tuple:
    """The reasons (DISTANCE_REASONS) of a packet's `distance_packet` codes (one byte per
    sample), one tuple per pattern of codes (a packet's in a dict lookup)."""
    return tuple(DISTANCE_REASONS[c] for c in codes)
