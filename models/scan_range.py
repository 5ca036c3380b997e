"""Scan range: the largest distance between any two measured points, kept up to date."""
from __future__ import annotations

import numpy as np

from models._kernels import SCAN_BLOCK, diameter_after_adding


class ScanRange:
    """Exact diameter (mm) of a growing point set, at most O(N) compiled work per new point.

    A new point can only raise the diameter through its distance to the points already
    in. Those are kept in blocks of SCAN_BLOCK consecutive points, each with a bounding
    ball about its first point; a block whose bound |p - c| + r cannot exceed the
    current diameter is skipped, so only the blocks across the scan from the new point
    are visited (consecutive A-scans lie close together: a block is a short arc of the
    scan). Exact, never an O(N^2) pass; coordinates centred on the first point.
    """

    def __init__(self, capacity: int = 8192):
        capacity = max(SCAN_BLOCK, -(-capacity // SCAN_BLOCK) * SCAN_BLOCK)
        self._X = np.empty((capacity, 3))
        self._block_r = np.zeros(capacity // SCAN_BLOCK)
        self._n = 0
        self._p0: np.ndarray | None = None
        self.diameter_mm = 0.0

    @property
    def n_points(self) -> int:
        return self._n

    def add(self, P: np.ndarray) -> float:
        """Add finite points P (N, 3) mm; return the updated diameter (mm)."""
        if len(P) and self._p0 is None:
            self._p0 = np.array(P[0], dtype=float)
        for p in P:
            if self._n == len(self._X):
                self._X = np.concatenate([self._X, np.empty_like(self._X)])
                self._block_r = np.concatenate([self._block_r, np.zeros_like(self._block_r)])
            self.diameter_mm = diameter_after_adding(self._X, self._block_r, self._n, p, self._p0, self.diameter_mm)
            self._n += 1
        return self.diameter_mm
