"""The iiOCT stream's health: degenerate streams injected (StreamFault) and detected
(StreamHealth).

A sensor can keep sending packets that carry nothing: every sample invalid, the same
distance again and again while the instrument moves (a frozen extractor or a repeated
buffer), or time stamps that no longer advance. None of these is a silent sensor, so an
age check on the packets' arrival alone does not see them.

Rule. A sample is *healthy* when it is valid, its time stamp is newer than every sample
before it, and it is not frozen: its distance differs from the previous valid sample's,
or the beam's origin moved less than FROZEN_MOTION_MM since that value first came (the distance noise,
about 20 um SD, never repeats a value bit for bit; a still instrument may). The filter's
sensor age is the age of the newest healthy sample, and the filter stops (zero velocity,
"stale sensor (<why>)") once it exceeds its limit (safety.FilterConfig.max_sensor_age_s,
45 ms): every stream fault is acted on within that limit plus one control period (and,
for a frozen value, the time the beam takes to move FROZEN_MOTION_MM), and the reason
names what the newest samples were. Units: mm, s.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FROZEN_MOTION_MM = 0.005  # beam origin's motion above which an unchanged distance is frozen
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
    "" while healthy); counts of the samples judged invalid, frozen and out of time order."""

    def __init__(self):
        self.healthy_t_s = -np.inf
        self.why = ""
        self.n_invalid = self.n_frozen = self.n_stale_stamps = 0
        self._last_t = -np.inf
        self._last_d = np.nan
        self._last_origin = np.full(3, np.nan)

    def update(self, t_s, valid, distance_mm, origin_W) -> float:
        """Judge a packet's samples (t_s (K,) s, valid (K,), distance (K,) mm, beam origins
        (K, 3) mm, in time order); returns healthy_t_s."""
        t_s = np.asarray(t_s)
        new = t_s > self._last_t
        if not new.all():
            self.n_stale_stamps += int((~new).sum())
            if not new.any():
                self.why = WHY["stuck_clock"]
                return self.healthy_t_s
        for k in np.flatnonzero(new).tolist():
            self._last_t = t_s[k]
            if not valid[k]:
                self.n_invalid += 1
                self.why = WHY["invalid"]
                continue
            d, o = distance_mm[k], origin_W[k]
            if d == self._last_d:  # the same value: frozen once the beam moved since it first came
                if np.sqrt(np.sum((o - self._last_origin) ** 2)) > FROZEN_MOTION_MM:
                    self.n_frozen += 1
                    self.why = WHY["frozen"]
                    continue
            else:
                self._last_d, self._last_origin = d, o
            self.healthy_t_s, self.why = t_s[k], ""
        return self.healthy_t_s
