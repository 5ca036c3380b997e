"""Progress display on stderr for the command line's long phases (tqdm); stdout is left to results.

- `progress_bar(total, desc)`: a bar for `total` units of work; call `.update(n=1)` after
  each unit and `.close()` at the end (or use it as a context manager).
- `phase(desc)`: a context manager for a phase of unknown length (a first-run compile,
  building a plan): after PHASE_DELAY_S it shows a spinner and the elapsed time on one
  stderr line, which it clears when the phase ends.

On a stream that is not a terminal (a log file, a batch job's output) both write whole
lines instead, which a log keeps readable: a bar a line at most every LINE_INTERVAL_S
while it advances (and a last one when it closes, if it wrote any), a phase a line when
it has lasted PHASE_DELAY_S and one with its duration when it ends. Both show nothing
when VITREOGUARD_NO_PROGRESS=1 is set (the tests set it) or, for a bar, when `total` is
below MIN_TOTAL.
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
LINE_INTERVAL_S = 10.0  # off a terminal: a bar's lines at most this often


def _stream(stream):
    return sys.stderr if stream is None else stream


def turned_off() -> bool:
    """Whether VITREOGUARD_NO_PROGRESS turns progress off."""
    return os.environ.get(ENV_DISABLE, "").strip() not in ("", "0")


def enabled(stream=None) -> bool:
    """Whether a terminal's progress (bars and spinners) may be shown on `stream` (default stderr)."""
    if turned_off():
        return False
    isatty = getattr(_stream(stream), "isatty", None)
    return bool(isatty and isatty())


class LineBar:
    """A bar off a terminal: a whole line 'desc: n/total unit (p %), t s' at most every
    LINE_INTERVAL_S while it advances, and a last one on close if it wrote any; tqdm's
    `n`, `update`, `close` and context manager."""

    def __init__(self, total: int, desc: str, unit: str, stream):
        self.total, self.desc, self.unit, self.stream, self.n = total, desc, unit, stream, 0
        self._t0 = self._last = time.monotonic()
        self._wrote = self._closed = False

    def _line(self, now: float) -> None:
        pct = 100.0 * self.n / self.total if self.total else 100.0
        print(f"{self.desc}: {self.n}/{self.total} {self.unit} ({pct:.0f} %), {now - self._t0:.0f} s",
              file=self.stream, flush=True)
        self._last, self._wrote = now, True

    def update(self, n: int = 1) -> None:
        self.n += n
        now = time.monotonic()
        if n and now - self._last >= LINE_INTERVAL_S:
            self._line(now)

    def close(self) -> None:
        if not self._closed and self._wrote:
            self._line(time.monotonic())
        self._closed = True

    def __enter__(self) -> LineBar:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def progress_bar(total: int, desc: str, *, unit: str = "it", stream=None):
    """A tqdm bar on stderr (or `stream`) for `total` units of `unit`, labelled `desc`, on
    a terminal; a LineBar elsewhere; disabled (every call a no-op) when progress is
    turned off or `total` < MIN_TOTAL."""
    total, terminal = int(total), enabled(stream)
    if total >= MIN_TOTAL and not terminal and not turned_off():
        return LineBar(total, desc, unit, _stream(stream))
    return tqdm(total=total, desc=desc, unit=unit, file=_stream(stream), disable=total < MIN_TOTAL or not terminal,
                leave=False, dynamic_ncols=True, mininterval=0.25)


@contextmanager
def phase(desc: str, *, stream=None, delay_s: float = PHASE_DELAY_S):
    """Within the block, a spinner line '<spinner> desc <elapsed>' on stderr (or `stream`) from
    `delay_s` seconds on, refreshed by a daemon thread; cleared when the block exits,
    however it exits (an exception or Ctrl-C included)."""
    if turned_off():
        yield
        return
    if not enabled(stream):  # off a terminal: a line when it has lasted delay_s, one when it ends
        with _phase_lines(desc, _stream(stream), delay_s):
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


@contextmanager
def _phase_lines(desc: str, stream, delay_s: float):
    """phase's lines off a terminal: 'desc ...' once the block has lasted `delay_s` (a
    daemon thread's timer), 'desc: N s' when it ends after that line."""
    t0, started = time.monotonic(), threading.Event()

    def announce() -> None:
        started.set()
        print(f"{desc} ...", file=stream, flush=True)

    timer = threading.Timer(delay_s, announce)
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
        timer.join()
        if started.is_set():
            print(f"{desc}: {time.monotonic() - t0:.0f} s", file=stream, flush=True)
