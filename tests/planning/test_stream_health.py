"""Degenerate iiOCT streams: injected by StreamFault, judged by StreamHealth (the rule the
filter's sensor age follows: planning.iioct.stream)."""
from __future__ import annotations

import numpy as np
import pytest

from planning.iioct.packet import SensorPacket
from planning.iioct.stream import WHY, StreamFault, StreamHealth


def packet(t0: float, k: int = 20, rate: float = 2000.0, speed_mm_s: float = 5.0, seed: int = 0) -> SensorPacket:
    """A healthy packet: k samples from t0 at `rate`, the beam origin moving along x, the
    distance 10 mm with 20 um noise."""
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(k) / rate
    origin = np.column_stack([speed_mm_s * t, np.zeros(k), np.zeros(k)])
    u = np.tile([0.0, 0.0, 1.0], (k, 1))
    d = 10.0 + rng.normal(0.0, 0.02, k)
    return SensorPacket(t_s=t, distance_mm=d, valid=np.ones(k, dtype=bool), confidence=np.ones(k), p_W=origin + d[:, None] * u,
                        beam_origin_W=origin, beam_dir_W=u, true_distance_mm=np.full(k, 10.0), reasons=("",) * k,
                        ascans=None)


def stream(fault: StreamFault, packets: int = 10):
    """(healthy_t_s, why) after each packet of a 100 Hz stream of 20-sample packets with `fault`."""
    health, previous, out = StreamHealth(), None, []
    for i in range(packets):
        p = fault.apply(packet(0.01 * i, seed=i), previous)
        if p is not None:
            previous = p
            health.update(p.t_s, p.valid, p.distance_mm)
        else:
            health.why = WHY["dropout"]
        out.append((health.healthy_t_s, health.why))
    return out, health


def test_a_healthy_stream_is_healthy_to_its_last_sample():
    out, health = stream(StreamFault())
    assert out[-1] == (pytest.approx(0.09 + 19 / 2000.0), "")
    assert health.n_invalid == health.n_frozen == health.n_stale_stamps == 0


@pytest.mark.parametrize("kind", ["invalid", "frozen", "stuck_clock", "dropout"])
def test_every_degenerate_stream_stops_the_healthy_time_at_its_onset_and_says_why(kind):
    out, _ = stream(StreamFault(kind, onset_s=0.05))
    last_healthy = out[4][0]  # the packet before the onset (0.04 s .. 0.0495 s)
    assert last_healthy == pytest.approx(0.04 + 19 / 2000.0)
    # nothing from the onset's packet on counts, a frozen value's repeats included
    assert all(t == last_healthy for t, _ in out[5:])
    assert out[-1][1] == WHY[kind]


@pytest.mark.parametrize("speed_mm_s", [0.0, 0.1, 5.0])
def test_a_repeated_distance_is_frozen_however_the_instrument_moves(speed_mm_s):
    health = StreamHealth()
    p = packet(0.0, speed_mm_s=speed_mm_s)._replace(distance_mm=np.full(20, 10.0))
    health.update(p.t_s, p.valid, p.distance_mm)
    # the first sample is a measurement; its 19 repeats carry none
    assert health.healthy_t_s == p.t_s[0] and health.n_frozen == 19 and health.why == WHY["frozen"]
    q = packet(0.01, speed_mm_s=speed_mm_s, seed=1)  # fresh, noisy distances: healthy again
    health.update(q.t_s, q.valid, q.distance_mm)
    assert health.healthy_t_s == q.t_s[-1] and health.why == ""


def test_a_bad_fault_is_refused():
    with pytest.raises(ValueError, match="StreamFault.kind"):
        StreamFault("silence")
    with pytest.raises(ValueError, match="onset_s"):
        StreamFault("invalid", onset_s=np.nan)
