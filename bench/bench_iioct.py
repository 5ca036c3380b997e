"""iiOCT sensor figures: per-A-scan synthesis and extraction time."""
from __future__ import annotations

import numpy as np

from bench.timing import summary_us, time_calls_us
from models.iioct import DistanceExtractor, OctEngine, synthesize_ascan


def run() -> None:
    engine = OctEngine()
    rng = np.random.default_rng(0)
    n = 2000
    d = rng.uniform(0.5, 25.0, n)
    th = rng.uniform(0.0, np.deg2rad(45.0), n)
    scans = []
    t = time_calls_us(lambda i: scans.append(synthesize_ascan(d[i], th[i], rng, engine=engine)), n)
    print(f"  synthesize_ascan ({engine.n_samples} samples), 0.5-25 mm, 0-45 deg: {summary_us(t)}")
    extract = DistanceExtractor(engine)
    out = []
    t = time_calls_us(lambda i: out.append(extract(scans[i])), n)
    print(f"  DistanceExtractor per A-scan (2 kHz budget: 500 us):      {summary_us(t)}")
    valid = np.array([m.valid for m in out])
    err = np.array([m.distance_mm for m in out])[valid] - d[valid]
    print(f"  on these scans: {valid.mean():.1%} valid, error mean {1e3 * err.mean():.1f} um, "
          f"SD {1e3 * err.std():.1f} um, p99 |error| {1e3 * np.percentile(np.abs(err), 99):.0f} um")
