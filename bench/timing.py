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
