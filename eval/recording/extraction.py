"""Every A-scan of a recording through the project's extractor (models.iioct
DistanceExtractor), in worker processes.

The extractor takes about 0.1 ms per A-scan in Python (peak search, template matching,
sub-sample refinement: models.iioct.segmentation), so a 2-minute recording's 240,000
A-scans are its longest step; the bag's reader (rosbags, one process) takes about a
third of that. The A-scans go to `jobs` forked processes in blocks of BLOCK (as float32:
the bag holds 16-bit counts or 32-bit floats, so nothing is lost), at most 2 blocks per
worker in flight, and come back in order; with jobs = 1 they are extracted in this
process. The result does not depend on `jobs`: each A-scan's distance is a function of
that A-scan alone.

Units: mm.
"""
from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from models.iioct import DistanceExtractor, OctEngine

BLOCK = 2000

_WORKER = []  # the worker process's extractor, built once by _start


def _start(engine: OctEngine) -> None:
    _WORKER.clear()
    _WORKER.append(DistanceExtractor(engine))


def extract_block(A: np.ndarray, extractor: DistanceExtractor | None = None) -> tuple[np.ndarray, np.ndarray]:
    """((M,) distance mm, NaN where invalid; (M,) confidence) of the A-scans A (M, n)."""
    ex = _WORKER[0] if extractor is None else extractor
    d, c = np.empty(len(A)), np.empty(len(A))
    for i, a in enumerate(A):
        m = ex(a.astype(np.float64))
        d[i], c[i] = (m.distance_mm if m.valid else np.nan), m.confidence
    return d, c


class Extraction:
    """A sink for read_bag's A-scans (call it with each one, in order), then `result()`:
    ((N,) distances mm, NaN where invalid; (N,) confidences). Use as a context manager
    (the workers end with it)."""

    def __init__(self, engine: OctEngine, jobs: int = 1):
        self.engine, self.jobs = engine, int(jobs)
        self._block: list[np.ndarray] = []
        self._pending, self._done = [], []
        self._pool = None
        self._local = DistanceExtractor(engine) if self.jobs <= 1 else None

    def __enter__(self) -> Extraction:
        if self.jobs > 1:
            self._pool = ProcessPoolExecutor(self.jobs, mp_context=multiprocessing.get_context("fork"),
                                             initializer=_start, initargs=(self.engine,))
        return self

    def __exit__(self, *exc) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __call__(self, ascan: np.ndarray) -> None:
        self._block.append(np.asarray(ascan, dtype=np.float32))
        if len(self._block) == BLOCK:
            self._submit()

    def _submit(self) -> None:
        if not self._block:
            return
        A = np.stack(self._block)
        self._block = []
        if self._pool is None:
            self._done.append(extract_block(A, self._local))
            return
        self._pending.append(self._pool.submit(extract_block, A))
        while len(self._pending) > 2 * self.jobs:  # bounded memory: wait for the oldest block
            self._done.append(self._pending.pop(0).result())

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        self._submit()
        while self._pending:
            self._done.append(self._pending.pop(0).result())
        if not self._done:
            return np.empty(0), np.empty(0)
        return np.concatenate([d for d, _ in self._done]), np.concatenate([c for _, c in self._done])
