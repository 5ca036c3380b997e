"""The sensor's joint-angle register: the joint angles latched at the rate at which they
change, which latch each sample takes, and the samples a register of latches covers.

The OCT engine samples at rate_hz; the joint angles q are a zero-order hold that changes
only at whole multiples of 1 / input_rate_hz (input_rate_hz = rate_hz / ratio). Latch j
holds q at time j / input_rate_hz; sample k, at k / rate_hz, takes the q of latch
ceil(k / ratio): the value q holds during ((j - 1) / input_rate_hz, j / input_rate_hz],
which a latch at every sample time would record at each sample of that interval. A
register holds rows [recorded flag (1 once written), q (6) rad] of the newest `slots`
latches, oldest first: those covering a packet's samples, those of the time offset's
history before them, and one older still, the sentinel, whose samples are never read (a
recorded sentinel shows, from the register alone, that the run started before every
sample the other rows cover).

Units: s, Hz, rad.
"""
from __future__ import annotations

import numpy as np

REGISTER_ROW = 7  # a register row: [recorded flag, q (6) rad]


def rate_ratio(rate_hz: float, input_rate_hz: float) -> int | None:
    """r if rate_hz / input_rate_hz (both Hz) is an integer r >= 1 within a relative 1e-9
    (input_rate_hz finite and > 0), else None."""
    ratio = rate_hz / input_rate_hz if np.isfinite(input_rate_hz) and input_rate_hz > 0 else np.nan
    if not np.isfinite(ratio):
        return None
    r = round(ratio)
    return r if r >= 1 and abs(ratio - r) <= 1e-9 * ratio else None


class JointRegister:
    """The register of a sensor sampling at `rate_hz` with `ratio` samples per latch,
    delivering packets of `packet` samples (a multiple of ratio) with `history` samples
    kept before each packet (the time offset's interpolation).

    A packet is read a quarter of a sample period after the latch that covers its last
    sample: `offset_s` (s) for the first packet, then every packet / rate_hz s; that
    latch is `lag` (0 or 1) samples after the packet's last sample. `slots`: the latches
    the register holds (the sentinel included). Sample k is stamped k x period_s, the
    time of a latch at every sample bit for bit (Drake's periodic event times)."""

    def __init__(self, rate_hz: float, ratio: int, packet: int, history: int):
        self.period_s, self.ratio, self.packet = 1.0 / rate_hz, ratio, packet
        last = packet - 1  # the first packet's last sample
        latched = -(-last // ratio) * ratio  # the sample at the time of the latch covering it
        self.lag = latched - last  # the same for every packet (packet is a multiple of ratio)
        # latches 0 .. latched / ratio cover samples 0 .. last, history // ratio more the history before
        # them, and one more is the sentinel
        self.slots = latched // ratio + history // ratio + 2
        # with the sentinel recorded: the samples rows 1 .. slots - 1 cover, counted from the sentinel's
        # last one, and the register's entries of their joint angles (sample i in row 1 + i // ratio)
        self._covered = np.arange((self.slots - 1) * ratio - self.lag)
        self._covered_q = REGISTER_ROW * (1 + self._covered // ratio)[:, None] + np.arange(1, REGISTER_ROW)
        self.offset_s = (latched + 0.25) * self.period_s

    def newest_latch(self, t_s: float) -> int:
        """The index of the newest latch at a read's time t_s (s, a quarter sample after a sample)."""
        return round(t_s / self.period_s - 0.25) // self.ratio

    def recorded_full(self, register: np.ndarray, t_s: float) -> tuple[np.ndarray, np.ndarray] | None:
        """((K,) time stamps s, (K, 6) joint angles rad) of every sample the latches but the
        sentinel cover, oldest first, read at time t_s from `register` (slots x 7,
        flattened) when its sentinel is recorded; else None. Once the sentinel is recorded
        so is every later latch, and the run started at or before the sentinel's latch, a
        sample period or more before the first sample the other rows cover: all their
        samples count, read with precomputed indices and without the start time
        (`recorded_since`'s arrays there, bit for bit)."""
        sentinel = self.newest_latch(t_s) - self.slots + 1
        if register[0] == 1.0 and sentinel >= 0:
            return (sentinel * self.ratio + 1 + self._covered) * self.period_s, register[self._covered_q]
        return None

    def recorded_since(self, register: np.ndarray, t_s: float, start_s: float) -> tuple[np.ndarray, np.ndarray]:
        """`recorded_full`'s arrays in any state of the register: the samples the recorded
        latches but the sentinel cover, at or after the run's start time start_s (s), up
        to the packet's last sample (`lag` before the newest latch)."""
        rows = register.reshape(self.slots, REGISTER_ROW)[1:]  # the sentinel's samples are never packed
        if rows[0, 0] != 1.0:  # not full yet: the recorded rows are the newest
            rows = rows[rows[:, 0] == 1.0]
        r = self.ratio
        newest = self.newest_latch(t_s)
        oldest = newest - len(rows) + 1
        K = np.arange(max((oldest - 1) * r + 1, 0), newest * r - self.lag + 1)  # the samples they cover
        K = K[K * self.period_s >= start_s]
        return K * self.period_s, rows[-(-K // r) - oldest, 1:]  # sample k in latch ceil(k / r)


def delayed_angles(T: np.ndarray, T_all: np.ndarray, Q_all: np.ndarray, time_offset_s: float) -> np.ndarray:
    """Joint angles (M, 6) rad at the times T (M,) s minus time_offset_s (s, >= 0), from
    the recorded samples (times T_all (K,) s, joint angles Q_all (K, 6) rad, the last M
    at T): linear interpolation, held at the first sample before it."""
    if time_offset_s == 0.0:
        return Q_all[-len(T):]
    return np.column_stack([np.interp(T - time_offset_s, T_all, Q_all[:, i]) for i in range(6)])
