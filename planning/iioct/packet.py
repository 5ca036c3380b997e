"""The sensor's output types: one sample (`SensorSample`) and a packet of samples as arrays
(`SensorPacket`), and the packet before the first (`NO_SAMPLE_YET`).

Units: mm, s; frame W.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

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
    evaluation only). What `IioctSensor.packet` returns and the sensor system's "packet"
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
        return self._replace(**{name: getattr(self, name)[at] for name in PER_SAMPLE_ARRAYS},
                             reasons=tuple(self.reasons[k] for k in rows),
                             ascans=None if self.ascans is None else tuple(self.ascans[k] for k in rows))


# the fields of SensorPacket that are arrays with a row per sample
PER_SAMPLE_ARRAYS = tuple(f for f in SensorPacket._fields if f not in ("reasons", "ascans"))

NO_SAMPLE_YET = SensorPacket.invalid([-np.inf], "no_sample_yet")  # the sensor system's packet before its first


def scattered(items: tuple, at: np.ndarray, values) -> tuple:
    """`items` with items[at[i]] = values[i] (at: (L,) indices, values: L items)."""
    out = list(items)
    for k, v in zip(at.tolist(), values):
        out[k] = v
    return tuple(out)
