"""Timing helpers for the benchmarks."""
from __future__ import annotations

import time

import numpy as np


def time_calls_us(fn, n: int) -> np.ndarray:
    """Call fn(i) for i in range(n) and return each call's wall time in microseconds."""
    out = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter()
        fn(i)
        out[i] = (time.perf_counter() - t0) * 1e6
    return out


def summary_us(samples_us: np.ndarray) -> str:
    """'median X us, p99 Y us, max Z us' for a sample of durations in microseconds."""
    s = np.asarray(samples_us)
    return f"median {np.median(s):8.1f} us   p99 {np.percentile(s, 99):8.1f} us   max {s.max():8.1f} us"


def machine_stalls(duration_s: float = 1.0, threshold_us: float = 20.0) -> str:
    """How often this machine stops a busy Python loop for more than `threshold_us` (timer
    interrupts, the hypervisor, other processes): the floor under any p99 measured here.
    'N stalls > T us per second, median M us, max X us'."""
    stalls = []
    t_start = last = time.perf_counter()
    while last - t_start < duration_s:
        now = time.perf_counter()
        if now - last > threshold_us * 1e-6:
            stalls.append((now - last) * 1e6)
        last = now
    s = np.array(stalls) if stalls else np.zeros(1)
    return (f"{len(stalls) / duration_s:.0f} stalls > {threshold_us:g} us per second, "
            f"median {np.median(s):.0f} us, max {s.max():.0f} us")
