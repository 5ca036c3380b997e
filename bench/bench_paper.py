"""The paper experiment end to end: `vitreoguard paper` with one seed (target < 60 s on 2 cores)."""
from __future__ import annotations

import tempfile
import time

from eval.cli import main as cli_main


def run() -> None:
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        cli_main(["paper", "--out", out, "--seeds", "1"])
        print(f"vitreoguard paper, 6 shapes x 5,093 A-scans, 1 seed, 500 x 500 sampling: {time.perf_counter() - t0:.1f} s")
