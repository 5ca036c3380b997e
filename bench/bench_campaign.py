"""Campaign scaling: the adversarial campaign of `vitreoguard boundary` on all six shapes
(BENCH_CAMPAIGN_SCENARIOS per shape, default 1,000; 0.5 s each), side by side in one
process, in 2 worker processes and on a local Ray instance with 2 workers.

Per shape the loop and the spiral-built model are made once (not timed here); each
backend then runs the same campaign, whose figures must agree to 1e-12. Scaling
efficiency = wall(1 worker) / (2 x wall(2 workers)); Ray's overhead = wall(Ray, 2) /
wall(2 processes) - 1. The machine's load average is printed beside: other processes on
the same cores take from the workers' share."""
from __future__ import annotations

import os
import time

import numpy as np

from eval.closed_loop import ClosedLoop, LoopConfig
from eval.experiments.boundary import build_model_by_spiral, run_campaign
from eval.experiments.campaign import LOCAL_RAY, Workers
from models.eyes import EYE_SHAPES
from planning import SurgeryScenario

SCENARIOS = int(os.environ.get("BENCH_CAMPAIGN_SCENARIOS", "1000"))
FIGURES = ("violations", "contacts", "min_true_clearance_mm")


def _ray_available() -> bool:
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


def run() -> None:
    backends = {"1 process": Workers(jobs=1), "2 processes": Workers(jobs=2)}
    if _ray_available():
        backends["Ray, 2 workers"] = Workers(jobs=2, ray=LOCAL_RAY)
    wall = dict.fromkeys(backends, 0.0)
    setup_s, ray_start_s = 0.0, None
    print(f"{len(EYE_SHAPES)} shapes x {SCENARIOS} scenarios of 0.5 s; load average before: {os.getloadavg()[0]:.2f}")
    for shape in EYE_SHAPES:
        t0 = time.perf_counter()
        loop = ClosedLoop(SurgeryScenario(eye_name=shape), LoopConfig(), sensor_seed=0)
        build = build_model_by_spiral(loop, sensor_seed=0)
        setup_s += time.perf_counter() - t0
        figures = {}
        for name, workers in backends.items():
            if workers.ray is not None and ray_start_s is None:  # start Ray once, outside the timed campaigns
                from eval.experiments.campaign import connect_ray

                t0 = time.perf_counter()
                connect_ray(workers)
                ray_start_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            c = run_campaign(loop, build.model, build.coverage, SCENARIOS, seed=0, workers=workers)
            wall[name] += time.perf_counter() - t0
            s = c.summary()
            figures[name] = [s[k] for k in FIGURES]
        ref = next(iter(figures.values()))
        same = all(np.allclose(v, ref, rtol=0, atol=1e-12) for v in figures.values())
        print(f"  {shape:10s} " + "  ".join(f"{n}: {wall[n]:7.1f} s" for n in backends) +
              f"   (cumulative) figures identical: {same}")
    print(f"setup (loops and spiral models, not in the walls): {setup_s:.1f} s; load average after: {os.getloadavg()[0]:.2f}")
    for name in backends:
        print(f"{name:16s} wall {wall[name]:7.1f} s for {len(EYE_SHAPES) * SCENARIOS} scenarios")
    print(f"scaling efficiency 1 -> 2 workers: {wall['1 process'] / (2 * wall['2 processes']):.2f} (target >= 0.8)")
    if "Ray, 2 workers" in wall:
        print(f"Ray (2 workers) vs 2 processes: {100 * (wall['Ray, 2 workers'] / wall['2 processes'] - 1):+.1f} % "
              f"(target within 15 %); Ray's start: {ray_start_s:.1f} s")
        import ray

        ray.shutdown()
