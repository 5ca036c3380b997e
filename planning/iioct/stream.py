"""The iiOCT stream's health: degenerate streams injected (StreamFault) and detected
(StreamHealth).

A sensor can keep sending packets that carry nothing: every sample invalid, the same
distance again and again while the instrument moves (a frozen extractor or a repeated
buffer), or time stamps that no longer advance. None of these is a silent sensor, so an
age check on the packets' arrival alone does not see them.

Rule. A sample is *healthy* when it is valid, its time stamp is newer than every sample
before it, and its distance differs from the previous valid sample's. A repeated distance
carries no new measurement: the 20 um distance noise (and the A-scan extractor's sub-sample
refinement) never repeats a value bit for bit, so a run of one value is a frozen extractor
or a repeated buffer, whether the instrument moves or not. The filter's sensor age is the
age of the newest healthy sample, and the filter stops (zero velocity, "stale sensor
(<why>)") once it exceeds its limit A (safety.FilterConfig.max_sensor_age_s, 45 ms); the
reason names what the newest samples were. Units: mm, s.

Detection within 50 ms. A fault with onset t_on degenerates every packet holding a sample
at or after t_on (StreamFault.apply): none of its samples is healthy (invalid, not newer,
a repeat of the last valid value, or no packet), so the newest healthy sample stays
before t_on. The filter checks the age at every control period dt_c (1 ms) and reads the
newest healthy time the model system relayed, which is never later than the newest
healthy sample (a packet arrives after its samples), so it stops at the first control
step after t_on + A at the latest: within A + dt_c = 46 ms of the onset, whatever the
instrument does. It does not stop earlier than A - T_p after the onset (T_p = 10 ms, the
packet period: the last healthy packet's newest sample is at most one packet period
before t_on). A healthy stream's newest sample is at most T_p plus the model's read
offset old when the filter reads it, far inside A.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FAULT_KINDS = ("none", "dropout", "invalid", "frozen", "stuck_clock")
WHY = {"invalid": "all samples invalid", "frozen": "frozen distances", "stuck_clock": "time stamps not advancing",
       "dropout": "no packets"}


@dataclass(frozen=True)
class StreamFault:
    """From `onset_s` (s, the run's time) on, the stream degenerates as `kind`: "dropout"
    (no new packets), "invalid" (every sample invalid), "frozen" (every distance the last
    valid one before the onset, its point rebuilt from it), "stuck_clock" (the packets'
    time stamps those of the last packet before the onset); "none": healthy."""

    kind: str = "none"
    onset_s: float = 0.1

    def __post_init__(self):
        if self.kind not in FAULT_KINDS:
            raise ValueError(f"StreamFault.kind must be one of {', '.join(FAULT_KINDS)}, got {self.kind!r}")
        if not (np.isfinite(self.onset_s) and self.onset_s >= 0):
            raise ValueError(f"StreamFault.onset_s must be >= 0 s, got {self.onset_s}")

    def apply(self, packet, previous):
        """The packet the stream delivers instead of `packet` (a SensorPacket; `previous` the
        last one delivered, or None): None for no new packet."""
        if self.kind == "none" or packet.t_s[-1] < self.onset_s:
            return packet
        if self.kind == "dropout":
            return None
        if self.kind == "invalid":
            return packet._replace(valid=np.zeros_like(packet.valid), p_W=np.full_like(packet.p_W, np.nan))
        if previous is None:
            return packet
        if self.kind == "stuck_clock":
            return packet._replace(t_s=previous.t_s.copy())
        ok = np.flatnonzero(previous.valid)
        if not len(ok):
            return packet
        d = previous.distance_mm[ok[-1]]
        distance = np.full_like(packet.distance_mm, d)
        return packet._replace(distance_mm=distance, valid=np.ones_like(packet.valid),
                               p_W=packet.beam_origin_W + d * packet.beam_dir_W)


class StreamHealth:
    """The stream's health over a run (module docstring): `healthy_t_s`, the newest healthy
    sample's time (-inf before one); `why`, what the samples since were (a WHY value, or
    "" while healthy); counts of the samples judged invalid, frozen (a repeated distance)
    and out of time order."""

    def __init__(self):
        self.healthy_t_s = -np.inf
        self.why = ""
        self.n_invalid = self.n_frozen = self.n_stale_stamps = 0
        self._last_t = -np.inf
        self._last_d = np.nan

    def update(self, t_s, valid, distance_mm) -> float:
        """Judge a packet's samples (t_s (K,) s, valid (K,), distance (K,) mm, in time
        order); returns healthy_t_s."""
        t_s = np.asarray(t_s)
        new = t_s > self._last_t
        if not new.all():
            self.n_stale_stamps += int((~new).sum())
            if not new.any():
                self.why = WHY["stuck_clock"]
                return self.healthy_t_s
        # as Python floats and bools: the loop reads them one by one (no NumPy scalar per read)
        times, oks, distances = t_s.tolist(), np.asarray(valid).tolist(), np.asarray(distance_mm).tolist()
        for k in np.flatnonzero(new).tolist():
            self._last_t = times[k]
            if not oks[k]:
                self.n_invalid += 1
                self.why = WHY["invalid"]
                continue
            d = distances[k]
            if d == self._last_d:  # a repeat: no new measurement, the healthy time stays at the value's first
                self.n_frozen += 1
                self.why = WHY["frozen"]
                continue
            self._last_d = d
            self.healthy_t_s, self.why = times[k], ""
        return self.healthy_t_s
