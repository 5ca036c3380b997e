"""Logging cost: the same adversarial scenarios (emmetropic eye, 2 s each) unlogged and
logged step by step to an MCAP file (eval.log.writer.RunLogger, as `boundary` logs its
scenario 0), alternately, with the wall time of the whole logged run (the file written
and closed) against the unlogged run's. Target: the logged realtime factor >= 1/2 of
the unlogged one."""
from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

from eval.closed_loop import ClosedLoop, LoopConfig
from eval.experiments.boundary import AdversarialScenario, build_model_by_spiral
from eval.log.writer import RunLogger
from planning import SurgeryScenario

SCENARIOS, DURATION_S = 5, 2.0


def run() -> None:
    loop = ClosedLoop(SurgeryScenario(eye_name="emmetropic"), LoopConfig(), sensor_seed=0)
    build = build_model_by_spiral(loop, sensor_seed=0)
    task = AdversarialScenario(build.model, build.coverage, seed=0, duration_s=DURATION_S)
    unlogged = logged = 0.0
    size = 0
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(SCENARIOS + 1):  # the first pair warms both paths up, not counted
            t0 = time.perf_counter()
            task(loop, i)
            t1 = time.perf_counter()
            path = Path(tmp) / f"run{i}.mcap"
            with RunLogger(path, loop.config.filter) as log:
                task(loop, i, log)
            t2 = time.perf_counter()
            if i:
                unlogged, logged, size = unlogged + t1 - t0, logged + t2 - t1, size + path.stat().st_size
    sim = SCENARIOS * DURATION_S
    print(f"{SCENARIOS} scenarios x {DURATION_S:.0f} s (load average {os.getloadavg()[0]:.2f}): realtime factor unlogged "
          f"{sim / unlogged:.1f}, logged {sim / logged:.1f} (whole run, file closed): ratio {unlogged / logged:.2f} "
          f"(target >= 0.5); {size / sim / 1e3:.0f} kB per simulated s")
