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

from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import NamedTuple

import numba
import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import Diagram, DiagramBuilder, LeafSystem
from pydrake.systems.primitives import ConstantVectorSource, Selector, SelectorParams, ZeroOrderHold

from models.eyes import retina_hits
from models.iioct import DistanceExtractor, Floater, OctEngine, synthesize_ascan
from models.rays import incidences_rad
from planning.chain import chain_pose_into
from planning.robot import Robot

DEFAULT_MAX_INCIDENCE_RAD = np.radians(55.0)
DISTANCE_MODE_CONFIDENCE = 0.9  # of a valid "distance" mode sample
BAD_JOINT_STATE = "bad_joint_state: q must be 6 finite angles (rad)"  # the reason of a sample without finite angles


class SensorSample(NamedTuple):
    """One iiOCT sample: OCT time stamp `t_s`; extracted `distance_mm` (NaN when
    invalid); `valid`, `confidence`, `reason` ("" when valid, else a models.iioct
    REASONS entry, "incidence", "no_retina" or "bad_joint_state"); the reconstructed
    retinal point `p_W` (NaN when invalid); the reported (calibrated) beam
    `beam_origin_W`, `beam_dir_W`; the raw `ascan` (None in "distance" mode); the true
    distance along the true beam (what evaluation compares with; nothing in the loop
    reads it). One row of a SensorPacket (`SensorPacket.sample`). A named tuple (a tenth
    of a frozen dataclass's cost), compared by identity like an object (its arrays have
    no truth value), immutable by contract (its arrays too)."""

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

    __eq__ = object.__eq__
    __ne__ = object.__ne__
    __hash__ = object.__hash__

    def __deepcopy__(self, memo) -> SensorSample:
        return self  # immutable by contract: Drake copies abstract state values often


class SensorPacket(NamedTuple):
    """M iiOCT samples as arrays, sample m in row m (the fields of SensorSample): OCT
    time stamps `t_s` (M,) s; extracted `distance_mm` (M,) (NaN where invalid); `valid`
    (M,) bool; `confidence` (M,); `reasons`, a tuple of M str (SensorSample.reason's);
    the reconstructed retinal points `p_W` (M, 3) mm (NaN rows where invalid); the
    reported (calibrated) beams' origins `beam_origin_W` (M, 3) mm and unit directions
    `beam_dir_W` (M, 3); `ascans`, a tuple of the M raw A-scans ("ascan" mode; None for
    a sample without one) or None when the packet has none ("distance" mode); the true
    distances `true_distance_mm` (M,) along the true beams (simulation ground truth, for
    evaluation only). What `IioctSensor.packet` returns and IioctSensorSystem's "packet"
    output carries: the loop reads it with array operations, no object per sample.
    `n_samples` is M; `sample(k)` and `samples()` give SensorSamples. Compared by
    identity like an object, immutable by contract (its arrays too): Drake copies
    abstract values often, and a deep copy is the packet itself."""

    t_s: np.ndarray
    distance_mm: np.ndarray
    valid: np.ndarray
    confidence: np.ndarray
    reasons: tuple
    p_W: np.ndarray
    beam_origin_W: np.ndarray
    beam_dir_W: np.ndarray
    ascans: tuple | None
    true_distance_mm: np.ndarray

    __eq__ = object.__eq__
    __ne__ = object.__ne__
    __hash__ = object.__hash__

    def __deepcopy__(self, memo) -> SensorPacket:
        return self

    @classmethod
    def invalid(cls, t_s, reason: str) -> SensorPacket:
        """M invalid samples at the times t_s (M,) s, each for `reason`: NaN distances,
        points and beams, confidence 0, no A-scans."""
        T = np.array(t_s, dtype=float).reshape(-1)
        M = len(T)
        return cls(T, np.full(M, np.nan), np.zeros(M, dtype=bool), np.zeros(M), (reason,) * M,
                   *(np.full((M, 3), np.nan) for _ in range(3)), None, np.full(M, np.nan))

    @property
    def n_samples(self) -> int:
        """M, the number of samples."""
        return len(self.t_s)

    def sample(self, k: int) -> SensorSample:
        """Sample k (0 <= k < M, or -M <= k < 0 counting from the last) as a SensorSample
        (its arrays are rows of the packet's)."""
        M = len(self.t_s)
        if not -M <= k < M:
            raise ValueError(f"k must be in [{-M}, {M - 1}] (a sample of the {M}), got {k}")
        return SensorSample(float(self.t_s[k]), float(self.distance_mm[k]), bool(self.valid[k]),
                            float(self.confidence[k]), self.reasons[k], self.p_W[k], self.beam_origin_W[k],
                            self.beam_dir_W[k], None if self.ascans is None else self.ascans[k],
                            float(self.true_distance_mm[k]))

    def samples(self) -> list[SensorSample]:
        """The M samples as SensorSamples, in order (their arrays are rows of the packet's)."""
        return [self.sample(k) for k in range(len(self.t_s))]

    def take(self, at: np.ndarray) -> SensorPacket:
        """The packet of the L samples at the indices `at` (L,) ints in [-M, M), in that
        order (the arrays' rows copied)."""
        rows = at.tolist()
        return self._replace(**{name: getattr(self, name)[at] for name in _PER_SAMPLE_ARRAYS},
                             reasons=tuple(self.reasons[k] for k in rows),
                             ascans=None if self.ascans is None else tuple(self.ascans[k] for k in rows))


# the fields of SensorPacket that are arrays with a row per sample
_PER_SAMPLE_ARRAYS = tuple(f for f in SensorPacket._fields if f not in ("reasons", "ascans"))


@numba.njit(cache=True)
def _grid_cell(grid, x):
    """(i, u): the cell [grid[i], grid[i + 1]] of x (clamped to the grid's first and last
    cells) and x's fraction u in [0, 1] across it (clamped)."""
    i = min(max(np.searchsorted(grid, x) - 1, 0), len(grid) - 2)
    return i, min(max((x - grid[i]) / (grid[i + 1] - grid[i]), 0.0), 1.0)


@numba.njit(cache=True)
def _cell(D, A, d, a):
    """(i, j, u, v): the cell [D[i], D[i + 1]] x [A[j], A[j + 1]] of the grid D x A that
    holds (d, a) and the fractions u, v across it (both clamped as in `_grid_cell`)."""
    i, u = _grid_cell(D, d)
    j, v = _grid_cell(A, a)
    return i, j, u, v


@numba.njit(cache=True)
def _bilinear_at(tables, cell, k):
    """Table k of `tables` (len(D), len(A), K) interpolated bilinearly in `cell` (`_cell`)."""
    i, j, u, v = cell
    return ((1 - u) * (1 - v) * tables[i, j, k] + u * (1 - v) * tables[i + 1, j, k]
            + (1 - u) * v * tables[i, j + 1, k] + u * v * tables[i + 1, j + 1, k])


@numba.njit(cache=True)
def bilinear(D, A, tables, d, a):
    """(M, K) the K tables (len(D), len(A), K) interpolated bilinearly at the M points
    (d[m], a[m]), clamped at the grid's edges."""
    out = np.empty((len(d), tables.shape[2]))
    for m in range(len(d)):
        cell = _cell(D, A, d[m], a[m])
        for k in range(tables.shape[2]):
            out[m, k] = _bilinear_at(tables, cell, k)
    return out


@numba.njit(cache=True)
def _draw_one(D, A, tables, d, a, uniform, normal):
    """(extracted distance mm, NaN when invalid; valid) of one sample at the true distance
    d mm and incidence a rad from its draws `uniform` in [0, 1) and `normal` (standard):
    invalid where uniform < p_invalid, else d + bias + sd normal (tables as in
    `bilinear`: p_invalid, bias mm, sd mm)."""
    cell = _cell(D, A, d, a)
    if uniform < _bilinear_at(tables, cell, 0):
        return np.nan, False
    return d + _bilinear_at(tables, cell, 1) + _bilinear_at(tables, cell, 2) * normal, True


@numba.njit(cache=True)
def _draw(D, A, tables, d, a, uniform, normal):
    """((M,) extracted distances mm, NaN where invalid; (M,) valid): `_draw_one` of the M
    samples (true distances d mm, incidences a rad, draws uniform and normal (M,))."""
    out, valid = np.empty(len(d)), np.empty(len(d), dtype=np.bool_)
    for m in range(len(d)):
        out[m], valid[m] = _draw_one(D, A, tables, d[m], a[m], uniform[m], normal[m])
    return out, valid


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

    @cached_property
    def _grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(D (n,) mm, A (k,) rad, tables (n, k, 3): p_invalid, bias mm, sd mm)."""
        return (np.array(self.distances_mm), np.array(self.incidences_rad),
                np.ascontiguousarray(np.stack([self.p_invalid, self.bias, self.sd], axis=-1), dtype=float))

    def interpolate(self, distances_mm: np.ndarray, incidences_rad: np.ndarray) -> np.ndarray:
        """(M, 3) [p_invalid, bias mm, sd mm] at M true distances (mm) and incidences (rad)
        (finite, M >= 0)."""
        D, A, tables = self._grid
        return bilinear(D, A, tables, np.ascontiguousarray(distances_mm, dtype=float),
                        np.ascontiguousarray(incidences_rad, dtype=float))

    def draws(self, distances_mm: np.ndarray, incidences_rad: np.ndarray,
              rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """((M,) extracted distances mm, NaN where invalid; (M,) valid) for M true distances
        (mm) and incidences (rad): one uniform (invalid with probability p_invalid) and one
        standard normal per sample, drawn in two batches from `rng`."""
        D, A, tables = self._grid
        d, a = np.ascontiguousarray(distances_mm, dtype=float), np.ascontiguousarray(incidences_rad, dtype=float)
        return _draw(D, A, tables, d, a, rng.random(len(d)), rng.standard_normal(len(d)))


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


@numba.njit(cache=True)
def _same_row(A, m, B, k) -> bool:
    """Whether row m of A equals row k of B (rows of joint angles; NaN equals nothing)."""
    for i in range(A.shape[1]):
        if A[m, i] != B[k, i]:
            return False
    return True


@numba.njit(cache=True)
def _beam_into(R, p, R_home, p_home, O, U, m):
    """O[m], U[m] <- the origin (mm) and z axis in W of the frame with home pose (R_home,
    p_home) on the chain's product (R, p) (chain_pose_into): planning.chain._apply's,
    bit for bit."""
    for r in range(3):
        U[m, r] = R[r, 0] * R_home[0, 2] + R[r, 1] * R_home[1, 2] + R[r, 2] * R_home[2, 2]
        O[m, r] = p[r] + (R[r, 0] * p_home[0] + R[r, 1] * p_home[1] + R[r, 2] * p_home[2])


@numba.njit(cache=True)
def sensor_beams(S, Q_true, Q_reported, R_true, p_true, R_cal, p_cal):
    """(O_true, U_true, O_cal, U_cal), each (M, 3) in W: the origins (mm) and z axes of
    the chain's (planning.chain) frames with home poses (R_true, p_true) at the rows of
    Q_true and (R_cal, p_cal) at the rows of Q_reported (M, n) rad: the true and the
    calibrated beam. A row equal to the one before (the sensor's latches hold the joint
    angles over several samples) repeats that row's beam; the chain is evaluated once per
    other row, and once more for a reported row that differs from its true one. Equal
    angles give equal beams bit for bit (signed zeros too: an angle of -0.0 or 0.0 gives
    the same product)."""
    M = Q_true.shape[0]
    O_true, U_true, O_cal, U_cal = np.empty((M, 3)), np.empty((M, 3)), np.empty((M, 3)), np.empty((M, 3))
    R, p, R_rep, p_rep, work = np.empty((3, 3)), np.empty(3), np.empty((3, 3)), np.empty(3), np.empty((2, 3, 3))
    for m in range(M):
        if m > 0 and _same_row(Q_true, m, Q_true, m - 1):
            O_true[m], U_true[m] = O_true[m - 1], U_true[m - 1]  # (R, p) stays the product at this row
        else:
            chain_pose_into(S, Q_true[m], R, p, work)
            _beam_into(R, p, R_true, p_true, O_true, U_true, m)
        if m > 0 and _same_row(Q_reported, m, Q_reported, m - 1):
            O_cal[m], U_cal[m] = O_cal[m - 1], U_cal[m - 1]
        elif _same_row(Q_reported, m, Q_true, m):
            _beam_into(R, p, R_cal, p_cal, O_cal, U_cal, m)
        else:
            chain_pose_into(S, Q_reported[m], R_rep, p_rep, work)
            _beam_into(R_rep, p_rep, R_cal, p_cal, O_cal, U_cal, m)
    return O_true, U_true, O_cal, U_cal


DISTANCE_REASONS = ("", "no_retina", "low_confidence")  # the reasons of `distance_packet`'s codes
_NO_RETINA, _LOW_CONFIDENCE = 1, 2  # their codes
_NO_FLOATER_DRAWS = np.empty((2, 0))  # distance_packet's floater draws without floaters


@numba.njit(cache=True)
def distance_packet(S, Q_true, Q_reported, R_true, p_true, R_cal, p_cal, eye, max_distance_mm, D, A, tables,
                    uniform, normal, floater_rate, floater_draws):
    """The arrays of a "distance" mode packet of M samples in one compiled pass: the true
    and calibrated beams at Q_true and Q_reported (M, 6) rad (`sensor_beams`, homes
    (R_true, p_true) and (R_cal, p_cal) in the chain S); the true retina's distance and
    incidence along the true beam (models.eyes.retina_hits with the eye's
    `Eye.hit_arguments` `eye`, one ray cast per run of equal rows of Q_true); a sample
    with no retina within max_distance_mm (mm) is invalid ("no_retina"), the others get
    the error model's draw (`_draw_one` with ExtractorErrorModel's grid D mm, A rad and
    `tables`) from uniform[m] and normal[m] (M,); then, with floater_rate > 0, a floater
    where floater_draws[0, m] < floater_rate on a beam longer than 1 mm: a valid distance
    0.5 + (d_true - 1) floater_draws[1, m] mm, uniform between 0.5 mm and 0.5 mm before
    the retina (floater_draws: (2, M) uniforms in [0, 1), not read without floaters).

    Returns (d (M,) mm, NaN where invalid; valid (M,) bool; confidence (M,)
    (DISTANCE_MODE_CONFIDENCE where valid, else 0); codes (M,) uint8, the indices of the
    samples' reasons in DISTANCE_REASONS; P_W (M, 3) mm = O_cal + d U_cal, NaN rows where
    invalid; O_cal, U_cal (M, 3) the calibrated beams; d_true (M,) mm, NaN without a
    hit). ValueError when the draws do not have M samples, or as retina_hits."""
    M = Q_true.shape[0]
    if len(uniform) != M or len(normal) != M or (floater_rate > 0.0 and floater_draws.shape[1] != M):
        raise ValueError("uniform and normal must be (M,) draws, and floater_draws (2, M) with floaters")
    O_true, U_true, O, U = sensor_beams(S, Q_true, Q_reported, R_true, p_true, R_cal, p_cal)
    # one ray cast per run of equal rows of Q_true (equal true beams): row m's is number at[m]
    at, first = np.empty(M, dtype=np.int64), np.empty(M, dtype=np.int64)
    n = 0
    for m in range(M):
        if m == 0 or not _same_row(Q_true, m, Q_true, m - 1):
            first[n] = m
            n += 1
        at[m] = n - 1
    hit_distance, hit_incidence = retina_hits(O_true[first[:n]], U_true[first[:n]], *eye)
    d_true = hit_distance[at]
    d, valid, confidence = np.full(M, np.nan), np.zeros(M, dtype=np.bool_), np.zeros(M)
    codes, P = np.zeros(M, dtype=np.uint8), np.full((M, 3), np.nan)
    for m in range(M):
        if not d_true[m] <= max_distance_mm:  # NaN: no hit
            codes[m] = _NO_RETINA
            continue
        d[m], valid[m] = _draw_one(D, A, tables, d_true[m], hit_incidence[at[m]], uniform[m], normal[m])
        if floater_rate > 0.0 and floater_draws[0, m] < floater_rate and d_true[m] > 1.0:
            d[m], valid[m] = 0.5 + (d_true[m] - 1.0) * floater_draws[1, m], True
        if not valid[m]:
            codes[m] = _LOW_CONFIDENCE
            continue
        confidence[m] = DISTANCE_MODE_CONFIDENCE
        for k in range(3):
            P[m, k] = O[m, k] + d[m] * U[m, k]
    return d, valid, confidence, codes, P, O, U, d_true


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


@numba.njit(cache=True)
def _all_finite(A, B) -> bool:
    """Whether every entry of A and B is finite."""
    for X in (A, B):
        for x in X.flat:
            if not np.isfinite(x):
                return False
    return True


@lru_cache(maxsize=4096)
def _distance_reasons(codes: bytes) -> tuple:
    """The reasons (DISTANCE_REASONS) of a packet's `distance_packet` codes (one byte per
    sample), one tuple per pattern of codes (a packet's in a dict lookup)."""
    return tuple(DISTANCE_REASONS[c] for c in codes)


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
        R_S, p_S = robot.chain.homes["S"]  # the calibrated frame's home pose: S's composed with X_S_Scal
        self._home_Scal = (np.ascontiguousarray(R_S @ np.asarray(R, dtype=float)), R_S @ np.asarray(p, dtype=float) + p_S)
        self.encoder_noise_rad = float(encoder_noise_rad)
        self.max_incidence_rad = float(max_incidence_rad)
        self.floater_rate = float(floater_rate)
        self._rng = np.random.default_rng(seed)
        self.max_distance_mm = self.engine.depth_mm / self.engine.group_index - self.engine.tip_offset_mm
        if mode == "distance":  # the packet's kernels loaded from numba's cache (compiled on a fresh
            # checkout) now, not inside the first packet of a timed closed-loop run; no draws taken
            q = np.zeros((1, 6))
            _all_finite(q, q)
            self._distance_arrays(q, q, np.zeros(1), np.zeros(1), np.zeros((2, 1)))

    def reported_beams(self, Q_reported) -> tuple[np.ndarray, np.ndarray]:
        """(origins (M, 3) mm, unit directions (M, 3)) in W of the calibrated beam at the
        reported joint angles Q_reported (M, 6) rad, finite (plus the encoder noise, drawn
        per sample)."""
        Q = self._with_encoder_noise(_finite_rows(Q_reported))
        return self._beams(Q, Q)[2:]

    def true_geometry(self, Q_true) -> tuple[np.ndarray, np.ndarray]:
        """((M,) true distances mm along the true beams at Q_true (M, 6) rad, finite, to
        the retina, NaN where there is none; (M,) incidences rad, NaN without a hit)."""
        Q = _finite_rows(Q_true)
        return self.eye.beam_hits(*self._beams(Q, Q)[:2])

    def _with_encoder_noise(self, Q: np.ndarray) -> np.ndarray:
        if self.encoder_noise_rad > 0:
            return Q + self.encoder_noise_rad * self._rng.standard_normal((len(Q), 6))
        return Q

    def _beams(self, Q_true: np.ndarray, Q_reported: np.ndarray) -> tuple:
        """(O_true, U_true, O_cal, U_cal) (M, 3): the true beams at Q_true and the
        calibrated ones at Q_reported, finite (M, 6) rad (sensor_beams)."""
        chain = self.robot.chain
        return sensor_beams(chain.S, np.ascontiguousarray(Q_true), np.ascontiguousarray(Q_reported),
                            *chain.homes["S_true"], *self._home_Scal)

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
        return self._packet(np.array(T_s, dtype=float).reshape(M), _joint_rows(Q_true, M), _joint_rows(Q_reported, M),
                            model)

    def _packet(self, T: np.ndarray, Qt: np.ndarray, Qr: np.ndarray, model) -> SensorPacket:
        """`packet` of the samples at times T (M,) s (the packet keeps T) from the joint
        angles Qt, Qr: C-contiguous (M, 6) float arrays (rad), NaN rows for bad joint states."""
        if _all_finite(Qt, Qr):
            return self._measure(T, Qt, Qr, model)
        M = len(T)
        good = np.flatnonzero(np.isfinite(Qt).all(axis=1) & np.isfinite(Qr).all(axis=1))
        out = SensorPacket.invalid(T, BAD_JOINT_STATE)
        if not len(good):
            return out
        part = self._measure(T[good], Qt[good], Qr[good], model)
        for name in _PER_SAMPLE_ARRAYS:
            getattr(out, name)[good] = getattr(part, name)
        return out._replace(reasons=_scattered(out.reasons, good, part.reasons),
                            ascans=None if part.ascans is None else _scattered((None,) * M, good, part.ascans))

    def _measure(self, T: np.ndarray, Qt: np.ndarray, Qr: np.ndarray, model) -> SensorPacket:
        """The packet of the samples at times T (M,) s (the packet keeps T) from finite
        joint angles Qt, Qr (M, 6) rad, C-contiguous (the encoder noise drawn first)."""
        Qr = self._with_encoder_noise(Qr)
        if self.mode == "distance":
            return self._distance_packet(T, Qt, Qr, model)
        O_true, U_true, O, U = self._beams(Qt, Qr)
        d_true, incidence = self.eye.beam_hits(O_true, U_true)
        M = len(T)
        live = d_true <= self.max_distance_mm  # False where the beam meets no retina (NaN)
        reasons = ["" if ok else "no_retina" for ok in live.tolist()]
        for k in self._oblique(model, O, U, live).tolist():
            live[k], reasons[k] = False, "incidence"
        d, valid, confidence = np.full(M, np.nan), np.zeros(M, dtype=bool), np.zeros(M)
        ascans = [None] * M
        for k in np.flatnonzero(live).tolist():
            ascans[k], m = self._ascan_one(float(d_true[k]), float(incidence[k]))
            d[k], valid[k], confidence[k], reasons[k] = m.distance_mm, m.valid, m.confidence, "" if m.valid else m.reason
        d[~valid] = np.nan
        P = O + d[:, None] * U  # NaN rows where invalid
        return SensorPacket(T, d, valid, confidence, tuple(reasons), P, O, U, tuple(ascans), d_true)

    def _distance_packet(self, T: np.ndarray, Qt: np.ndarray, Qr: np.ndarray, model) -> SensorPacket:
        """`_measure` in "distance" mode: `distance_packet` with M uniforms, M standard
        normals and, with floaters, 2 x M uniforms drawn in that order; a sample rejected
        for its incidence on `model` (if any) leaves its draws unused."""
        M, rng = len(T), self._rng
        uniform, normal = rng.random(M), rng.standard_normal(M)
        floater_draws = rng.random((2, M)) if self.floater_rate > 0 else _NO_FLOATER_DRAWS
        d, valid, confidence, codes, P, O, U, d_true = self._distance_arrays(Qt, Qr, uniform, normal, floater_draws)
        reasons = _distance_reasons(codes.tobytes())
        if model is not None:
            oblique = self._oblique(model, O, U, codes != _NO_RETINA)
            d[oblique], valid[oblique], confidence[oblique], P[oblique] = np.nan, False, 0.0, np.nan
            reasons = _scattered(reasons, oblique, ("incidence",) * len(oblique))
        return SensorPacket(T, d, valid, confidence, reasons, P, O, U, None, d_true)

    def _distance_arrays(self, Qt: np.ndarray, Qr: np.ndarray, uniform: np.ndarray, normal: np.ndarray,
                         floater_draws: np.ndarray) -> tuple:
        """`distance_packet` of this sensor's chain, eye, range and error model at the
        finite joint angles Qt, Qr (M, 6) rad (C-contiguous) with the draws uniform, normal
        (M,) and floater_draws (2, M) (read only with floaters)."""
        chain = self.robot.chain
        return distance_packet(chain.S, Qt, Qr, *chain.homes["S_true"], *self._home_Scal, self.eye.hit_arguments,
                               self.max_distance_mm, *self.error_model._grid, uniform, normal, self.floater_rate,
                               floater_draws)

    def _oblique(self, model, O: np.ndarray, U: np.ndarray, live: np.ndarray) -> np.ndarray:
        """The indices of the `live` (M,) samples whose calibrated beams (origins O, unit
        directions U (M, 3) in W) meet `model` (anything with ray_cast and gradient in W,
        or None: none) more obliquely than max_incidence_rad."""
        if model is None or not live.any():
            return np.empty(0, dtype=int)
        return np.flatnonzero(live)[_model_incidences(model, O[live], U[live]) > self.max_incidence_rad]

    def _ascan_one(self, d_true: float, incidence: float):
        """(A-scan, models.iioct extraction) of one sample with a retina at d_true mm and
        incidence rad in "ascan" mode, with a floater at the floater rate."""
        floater = self.floater_rate > 0 and d_true > 1.0 and self._rng.random() < self.floater_rate
        floaters = (Floater(float(self._rng.uniform(0.5, d_true - 0.5)), float(self._rng.uniform(35.0, 55.0))),) if floater else ()
        ascan = synthesize_ascan(d_true, incidence, self._rng, engine=self.engine, floaters=floaters)
        return ascan, self.extractor(ascan)


def _scattered(items: tuple, at: np.ndarray, values) -> tuple:
    """`items` with items[at[i]] = values[i] (at: (L,) indices, values: L items)."""
    out = list(items)
    for k, v in zip(at.tolist(), values):
        out[k] = v
    return tuple(out)


def _model_incidences(model, O: np.ndarray, U: np.ndarray) -> np.ndarray:
    """(M,) incidence (rad) of the beams (origins O, unit directions U (M, 3) in W) on
    `model` (anything with ray_cast and gradient in W); 0 where a beam misses it."""
    d = np.asarray(model.ray_cast(O, U), dtype=float)
    out = np.zeros(len(d))
    hit = np.isfinite(d)
    if hit.any():
        G = np.asarray(model.gradient(O[hit] + d[hit, None] * U[hit]), dtype=float)
        out[hit] = incidences_rad(np.ascontiguousarray(G), U[hit])
    return out


NO_SAMPLE_YET = SensorPacket.invalid([-np.inf], "no_sample_yet")  # IioctSensorSystem's packet before its first


def _shift_selector(rows: int) -> Selector:
    """A Selector giving the shift register's next value from its inputs "register"
    (`rows` rows of [recorded flag, q (6) rad], oldest first, flattened), "one" (1,) and
    "q" (6,) rad: the register without its oldest row, then [1, q]."""
    S = SelectorParams
    kept = [S.OutputSelection(input_port_index=0, input_offset=i) for i in range(7, 7 * rows)]
    new = [S.OutputSelection(input_port_index=1, input_offset=0)]
    new += [S.OutputSelection(input_port_index=2, input_offset=i) for i in range(6)]
    return Selector(S(inputs=[S.InputPortParams(name="register", size=7 * rows), S.InputPortParams(name="one", size=1),
                              S.InputPortParams(name="q", size=6)],
                      outputs=[S.OutputPortParams(name="shifted", selections=kept + new)]))


def rate_ratio(rate_hz: float, input_rate_hz: float) -> int | None:
    """r if rate_hz / input_rate_hz (both Hz) is an integer r >= 1 within a relative 1e-9
    (input_rate_hz finite and > 0), else None."""
    ratio = rate_hz / input_rate_hz if np.isfinite(input_rate_hz) and input_rate_hz > 0 else np.nan
    if not np.isfinite(ratio):
        return None
    r = round(ratio)
    return r if r >= 1 and abs(ratio - r) <= 1e-9 * ratio else None


class _PacketProcessor(LeafSystem):
    """Turns the latches' joint angles into the packet of the newest `packet` samples, in
    one unrestricted update at the packet rate (IioctSensorSystem). Latch j is taken at
    time j / input_rate (input_rate = rate_hz / `ratio`), sample k at k / rate_hz holds
    the q of latch ceil(k / ratio); the update runs a quarter of a sample period after
    the latch that covers each packet's last sample (`offset_s`, s, the first packet's
    update time). Input "register" (7 `slots`,): rows of [recorded flag, q (6) rad] of
    the newest `slots` latches, oldest first: the latches covering the packet and the
    `history` samples before it (the time offset's interpolation), and one older still,
    the sentinel, whose samples are never packed (a recorded sentinel shows, from the
    register alone, that the run started before every sample the other rows cover);
    outputs as IioctSensorSystem's."""

    def __init__(self, sensor: IioctSensor, rate_hz: float, ratio: int, time_offset_s: float, packet: int,
                 history: int):
        super().__init__()
        self.sensor, self.time_offset_s, self.packet, self._ratio = sensor, time_offset_s, packet, ratio
        self._period_s = 1.0 / rate_hz  # the sample period, s: sample k is at k * period (Drake's event time)
        last = packet - 1  # the first packet's last sample
        latched = -(-last // ratio) * ratio  # the sample at the time of the latch covering it
        self._lag = latched - last  # the same for every packet (packet is a multiple of ratio): 0 or 1 sample
        # latches 0 .. latched / ratio cover samples 0 .. last, history // ratio more the history before
        # them, and one more is the sentinel
        self.slots = latched // ratio + history // ratio + 2
        # with the sentinel recorded: the samples rows 1 .. slots - 1 cover, counted from the sentinel's
        # last one, and the register's entries of their joint angles (sample i in row 1 + i // ratio)
        self._covered = np.arange((self.slots - 1) * ratio - self._lag)
        self._covered_q = 7 * (1 + self._covered // ratio)[:, None] + np.arange(1, 7)
        self.offset_s = (latched + 0.25) * self._period_s
        self._register = self.DeclareVectorInputPort("register", 7 * self.slots)
        self._packet = self.DeclareAbstractState(AbstractValue.Make(NO_SAMPLE_YET))
        self._packet_at = int(self._packet)  # the same index as an int, which pybind takes faster per packet
        self._start = self.DeclareDiscreteState(1)  # the run's start time, s
        self.DeclareInitializationDiscreteUpdateEvent(self._set_start)
        self.DeclarePeriodicUnrestrictedUpdateEvent(packet * self._period_s, self.offset_s, self._process)
        packet_changed = {self.abstract_state_ticket(self._packet)}
        self.DeclareStateOutputPort("packet", self._packet)
        self.DeclareAbstractOutputPort("sample", lambda: AbstractValue.Make(NO_SAMPLE_YET.sample(0)),
                                       self._calc_sample, prerequisites_of_calc=packet_changed)
        self.DeclareVectorOutputPort("p_W", 3, self._calc_p, prerequisites_of_calc=packet_changed)
        self.DeclareVectorOutputPort("measurement", 4, self._calc_measurement, prerequisites_of_calc=packet_changed)

    def _set_start(self, context, discrete_state) -> None:
        discrete_state.set_value([context.get_time()])

    def _recorded(self, context) -> tuple[np.ndarray, np.ndarray]:
        """((K,) time stamps s, (K, 6) joint angles rad) of the samples covered by the
        recorded latches but the sentinel, from the run's start to the packet's last sample,
        oldest first. At the packet event's time t the newest latch is at sample round(t /
        period - 1/4) (`_newest_latch`), the packet's last sample `lag` before it; sample k
        is stamped k * period, the time of a register update at every sample, bit for bit,
        and counts from the run's start on (k * period >= the start time: Drake's first
        event of a periodic series that starts then). Once the sentinel is recorded (every
        packet of a run but the first one or two) so is every later latch, and the run
        started at or before the sentinel's latch, a sample period or more before the first
        sample the other rows cover: all their samples count, read off the register with
        precomputed indices and without the start time (the arrays `_recorded_since_start`
        gives there, bit for bit); otherwise `_recorded_since_start`."""
        register = self._register.Eval(context)
        sentinel = self._newest_latch(context) - self.slots + 1
        if register[0] == 1.0 and sentinel >= 0:
            return (sentinel * self._ratio + 1 + self._covered) * self._period_s, register[self._covered_q]
        return self._recorded_since_start(context)

    def _recorded_since_start(self, context) -> tuple[np.ndarray, np.ndarray]:
        """`_recorded` in any state: the recorded rows but the sentinel, their samples
        filtered by the run's start time (the initialisation event's)."""
        rows = self._register.Eval(context).reshape(self.slots, 7)[1:]  # the sentinel's samples are never packed
        if rows[0, 0] != 1.0:  # not full yet: the recorded rows are the newest
            rows = rows[rows[:, 0] == 1.0]
        r = self._ratio
        newest = self._newest_latch(context)
        oldest = newest - len(rows) + 1
        K = np.arange(max((oldest - 1) * r + 1, 0), newest * r - self._lag + 1)  # the samples they cover
        K = K[K * self._period_s >= context.get_discrete_state(self._start).GetAtIndex(0)]
        return K * self._period_s, rows[-(-K // r) - oldest, 1:]  # sample k in latch ceil(k / r)

    def _newest_latch(self, context) -> int:
        """The index of the newest latch at the packet event's time (a quarter sample after a sample)."""
        return round(context.get_time() / self._period_s - 0.25) // self._ratio

    def _process(self, context, state) -> None:
        T_all, Q_all = self._recorded(context)
        if not len(T_all):  # a run started after this packet's last sample: keep the previous packet
            return
        T, Q = T_all[-self.packet:], Q_all[-self.packet:]
        # IioctSensor.packet without its input conversions: these are C-contiguous float arrays already
        packet = self.sensor._packet(T, Q, self._reported(T, T_all, Q_all), None)
        state.get_mutable_abstract_state(self._packet_at).set_value(packet)

    def _reported(self, T: np.ndarray, T_all: np.ndarray, Q_all: np.ndarray) -> np.ndarray:
        """Joint angles (M, 6) rad at the times T - time_offset_s, from the recorded
        samples (times T_all (K,) s, joint angles Q_all (K, 6) rad)."""
        if self.time_offset_s == 0.0:
            return Q_all[-len(T):]
        return np.column_stack([np.interp(T - self.time_offset_s, T_all, Q_all[:, i]) for i in range(6)])

    def _latest(self, context) -> SensorPacket:
        return context.get_abstract_state(self._packet_at).get_value()

    def _calc_sample(self, context, value) -> None:
        value.set_value(self._latest(context).sample(-1))

    def _calc_p(self, context, output) -> None:
        output.SetFromVector(self._latest(context).p_W[-1])

    def _calc_measurement(self, context, output) -> None:
        p = self._latest(context)
        output.SetFromVector([p.distance_mm[-1], float(p.valid[-1]), p.confidence[-1], p.t_s[-1]])


class IioctSensorSystem(Diagram):
    """The sensor as a Drake block, sampling at `rate_hz` (default 2 kHz).

    Input "q" (6,) rad: the robot's joint angles. The OCT engine streams its A-scans in
    packets of `packet` samples (default 10, i.e. 5 ms at 2 kHz): each sample gets the
    joint angles held at its time, and the packet is processed once its last sample's
    angles are recorded (vectorised geometry). Outputs: "packet" (the latest packet, a
    SensorPacket; NO_SAMPLE_YET before the first), "sample" (its last sample, a
    SensorSample), "p_W" (3,) mm of that sample (NaN when invalid), "measurement" (4,)
    [distance_mm, valid 0/1, confidence, t_s] (t_s = -inf before the first packet).
    With `time_offset_s` (s) > 0 the points are reconstructed from the joint angles of
    `time_offset_s` earlier (the paper's OCT-robot synchronisation error, up to 2.6 ms),
    interpolated linearly in the recorded history.

    `input_rate_hz` (Hz; None: rate_hz) is the modelling assumption on q: a zero-order
    hold that changes only at whole multiples of 1 / input_rate_hz s (like the closed
    loop's DiscreteTimeIntegrator), an event at one of those times seeing the value
    before its change. rate_hz / input_rate_hz must be an integer r >= 1 (within a
    relative 1e-9) and `packet` a multiple of r. The joint angles are latched only at
    those times, j / input_rate_hz, and sample k (at k / rate_hz) takes those of latch
    ceil(k / r): the value q holds during ((j - 1) / input_rate_hz, j / input_rate_hz],
    which a register at every sample time would record at each sample of that interval.
    The packets are then those of r = 1, bit for bit, for one Drake step per latch
    instead of one per sample (half the steps for a 2 kHz sensor on 1 kHz joint angles);
    a q that changes between latches breaks the assumption: wrong angles, no warning.

    A diagram of Drake's C++ primitives and one Python system: a shift register (a
    ZeroOrderHold with period 1 / input_rate_hz and offset 0, i.e. Drake's discrete
    update at every latch time, its times computed like those of a
    DiscreteTimeIntegrator of that period, fed by a Selector from its own value, a
    constant 1 and "q") holds rows [recorded 1, q] of the latches covering the newest
    `packet` samples and the offset's history before them, and of one latch before those
    (whose flag tells the processor that the run started before them, without reading
    the start time); `_PacketProcessor` reads the whole register at the packet rate, a
    quarter of a sample period after the latch covering each packet's last sample
    (`packet_offset_s`, s, for the first packet, then every packet / rate_hz s: a
    quarter sample after the last sample for r = 1, 1.25 samples after it for r > 1),
    and stamps sample k with k / rate_hz as Drake computes it (k x period), a register
    update's time at every sample, bit for bit. A run started mid-packet packs only the
    samples at or after its start time (noted by an initialisation event). Not at the
    latch's own time: there the register would not hold that latch yet (events at one
    time see the state before them), and Drake computes each periodic series' times on
    its own (offset + k period), so coinciding times can differ by rounding and a packet
    event a few ulps after a register step be skipped (seen in the closed loop with the
    former 2 kHz Python recorder: one packet in 20 lost). A reader at the same time as
    the packet event sees the previous packet; the closed loop's model reads a quarter
    sample period after the packet event, the filter at whole control periods.
    """

    def __init__(self, sensor: IioctSensor, rate_hz: float = 2000.0, time_offset_s: float = 0.0, packet: int = 10,
                 input_rate_hz: float | None = None):
        super().__init__()
        if not (np.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz must be > 0 Hz, got {rate_hz}")
        if not (np.isfinite(time_offset_s) and 0 <= time_offset_s <= 0.1):
            raise ValueError(f"time_offset_s must be in [0, 0.1] s, got {time_offset_s}")
        if not (isinstance(packet, int) and 1 <= packet <= 1000):
            raise ValueError(f"packet must be an int in [1, 1000] samples, got {packet}")
        self.sensor, self.rate_hz, self.time_offset_s, self.packet = sensor, float(rate_hz), float(time_offset_s), packet
        if input_rate_hz is None:
            input_rate_hz = self.rate_hz
        ratio = rate_ratio(self.rate_hz, input_rate_hz)
        if ratio is None:
            raise ValueError(f"input_rate_hz must be rate_hz / r for an integer r >= 1 ({self.rate_hz:g}, "
                             f"{self.rate_hz / 2:g}, {self.rate_hz / 3:g}, ... Hz), got {input_rate_hz}")
        if packet % ratio:
            raise ValueError(f"packet must be a multiple of rate_hz / input_rate_hz = {ratio} samples, got {packet}")
        self.input_rate_hz = float(input_rate_hz)
        # samples recorded before the packet's, kept for the offset's interpolation
        history = int(np.ceil(time_offset_s * rate_hz)) + 1 if time_offset_s > 0 else 0
        b = DiagramBuilder()
        processor = b.AddSystem(_PacketProcessor(sensor, self.rate_hz, ratio, self.time_offset_s, packet, history))
        self.packet_offset_s = processor.offset_s  # s: the first packet's processing time (then every packet / rate_hz s)
        register = b.AddSystem(ZeroOrderHold(1.0 / self.input_rate_hz, 7 * processor.slots))
        shift = b.AddSystem(_shift_selector(processor.slots))
        one = b.AddSystem(ConstantVectorSource([1.0]))
        b.Connect(register.get_output_port(), shift.get_input_port(0))
        b.Connect(one.get_output_port(), shift.get_input_port(1))
        b.Connect(shift.get_output_port(0), register.get_input_port())
        b.Connect(register.get_output_port(), processor.GetInputPort("register"))
        b.ExportInput(shift.get_input_port(2), "q")
        for name in ("packet", "sample", "p_W", "measurement"):
            b.ExportOutput(processor.GetOutputPort(name), name)
        b.BuildInto(self)
