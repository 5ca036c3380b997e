"""Running the model's update at the OCT rate (2 kHz: one A-scan every 500 us) in Python.

What breaks the 500 us budget in a plain Python loop is not the update's own work but
Python's cyclic garbage collector. Every update keeps a few container objects (its
history entry, the criteria's checkpoints), so the collector runs from inside updates:
measured on the paper's spiral of the emmetropic eye, 8 passes (40,744 updates with the
local part): its young-generation passes took up to 0.18 ms, the middle generation's
0.63-0.77 ms, and one full pass over the 181,000 tracked objects 40 ms. The model's
update makes no reference cycles (tests/models/test_realtime.py): reference counting
frees everything it drops, and a stream may pause the collector for as long as it runs
without leaking. `collector_paused` does that for the length of a `with` block:

    with collector_paused():
        for p in stream:          # one A-scan (3,) mm, or a packet (N, 3)
            model.update(p)

The objects alive when it starts and those made during it are collected as usual once it
ends (one pass then, outside the stream). Code that makes reference cycles of its own
inside the block keeps them until the block ends; so does numba the first time it loads a
compiled function (a few ctypes types), which is one more reason to run the update once
before the stream starts (its first call loads the compiled kernels: seconds).
"""
from __future__ import annotations

import gc
from contextlib import contextmanager


@contextmanager
def collector_paused():
    """Pause Python's cyclic garbage collector for the block (module doc) and restore its
    state after it, also when the block raises; nested blocks leave it paused until the
    outermost ends."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


__all__ = ["collector_paused"]
