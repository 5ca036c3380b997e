"""A minimal progress bar on stderr for long runs (no dependency, no effect on stdout)."""
from __future__ import annotations

import sys
import time


class Progress:
    """`Progress(total, label)`; call `step(text)` after each unit of work."""

    def __init__(self, total: int, label: str, stream=None):
        self.total, self.label, self.done = max(int(total), 1), label, 0
        self.stream = sys.stderr if stream is None else stream
        self.t0 = time.perf_counter()

    def step(self, text: str = "") -> None:
        self.done += 1
        width = 30
        filled = int(width * self.done / self.total)
        elapsed = time.perf_counter() - self.t0
        self.stream.write(
            f"\r{self.label} [{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total} {elapsed:5.1f}s {text:<30}"
        )
        if self.done >= self.total:
            self.stream.write("\n")
        self.stream.flush()
