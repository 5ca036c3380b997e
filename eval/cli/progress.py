"""Progress display on stderr for the command line's long phases (tqdm); stdout is left to results.

- `progress_bar(total, desc)`: a bar for `total` units of work; call `.update(n=1)` after
  each unit and `.close()` at the end (or use it as a context manager).
- `phase(desc)`: a context manager for a phase of unknown length (a first-run compile,
  building a plan): after PHASE_DELAY_S it shows a spinner and the elapsed time on one
  stderr line, which it clears when the phase ends.

Both show nothing when VITREOGUARD_NO_PROGRESS=1 is set (the tests set it), when stderr
is not a terminal (a log file would fill with carriage returns), or, for a bar, when
`total` is below MIN_TOTAL.
"""
from __future__ import annotations

import os
import sys
import threading
import time
from contextlib import contextmanager

from tqdm import tqdm

ENV_DISABLE = "VITREOGUARD_NO_PROGRESS"
MIN_TOTAL = 2  # a bar over fewer units tells nothing
PHASE_DELAY_S = 2.0  # a phase shorter than this shows nothing
PHASE_REFRESH_S = 0.2  # the spinner's period
SPINNER = "|/-\\"


def enabled(stream=None) -> bool:
    """Whether progress may be shown on `stream` (default stderr)."""
    if os.environ.get(ENV_DISABLE, "").strip() not in ("", "0"):
        return False
    stream = sys.stderr if stream is None else stream
    isatty = getattr(stream, "isatty", None)
    return bool(isatty and isatty())


def progress_bar(total: int, desc: str, *, unit: str = "it", stream=None) -> tqdm:
    """A tqdm bar on stderr (or `stream`) for `total` units of `unit`, labelled `desc`;
    disabled (every call a no-op) when progress is off or `total` < MIN_TOTAL."""
    total = int(total)
    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr if stream is None else stream,
                disable=total < MIN_TOTAL or not enabled(stream), leave=False, dynamic_ncols=True,
                mininterval=0.25)


@contextmanager
def phase(desc: str, *, stream=None, delay_s: float = PHASE_DELAY_S):
    """Within the block, a spinner line '<spinner> desc <elapsed>' on stderr (or `stream`) from
    `delay_s` seconds on, refreshed by a daemon thread; cleared when the block exits,
    however it exits (an exception or Ctrl-C included)."""
    if not enabled(stream):
        yield
        return
    done = threading.Event()
    bar: list[tqdm] = []
    t0 = time.time()

    def spin() -> None:
        if done.wait(delay_s):
            return
        b = tqdm(total=None, desc=f"{SPINNER[0]} {desc}", file=sys.stderr if stream is None else stream, leave=False,
                 dynamic_ncols=True, bar_format="{desc} {elapsed}")
        b.start_t = t0  # the elapsed time of the whole phase, not of the line
        b.refresh()
        bar.append(b)
        k = 0
        while not done.wait(PHASE_REFRESH_S):
            k += 1
            b.set_description_str(f"{SPINNER[k % len(SPINNER)]} {desc}", refresh=True)

    thread = threading.Thread(target=spin, name=f"phase: {desc}", daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()
        for b in bar:
            b.close()
