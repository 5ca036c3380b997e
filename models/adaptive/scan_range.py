"""Scan range: the largest distance between any two measured points, kept up to date."""
from __future__ import annotations

import numpy as np

from models.adaptive.scan_range_kernels import SCAN_BLOCK, diameter_after_adding


class ScanRange:
    """Exact diameter (mm) of a growing point set, at most O(N) compiled work per new point.

    A new point can only raise the diameter through its distance to the points already
    in. Those are kept in blocks of SCAN_BLOCK consecutive points, each with a bounding
    ball about its first point; a block whose bound |p - c| + r cannot exceed the
    current diameter is skipped, so only the blocks across the scan from the new point
    are visited (consecutive A-scans lie close together: a block is a short arc of the
    scan); a batch's points first rule out blocks together, by their bounding ball.
    Exact, never an O(N^2) pass; coordinates centred on the first point.

    State, for models.adaptive.scan_range_kernels.diameter_after_adding: `X` (capacity, 3) the points less
    `p0` (the first point, mm) in its first `n_points` rows, `block_r` the blocks' radii
    (mm), `diameter_mm`.
    """

    def __init__(self, capacity: int = 8192):
        capacity = max(SCAN_BLOCK, -(-capacity // SCAN_BLOCK) * SCAN_BLOCK)
        self.X = np.empty((capacity, 3))
        self.block_r = np.zeros(capacity // SCAN_BLOCK)
        self._n = 0
        self.p0: np.ndarray | None = None
        self.diameter_mm = 0.0

    @property
    def n_points(self) -> int:
        return self._n

    def add(self, P: np.ndarray) -> float:
        """Add finite points P (N, 3) mm; return the updated diameter (mm)."""
        if len(P) and self.p0 is None:
            self.p0 = np.array(P[0], dtype=float)
        if len(P):
            self.reserve(len(P))
            self.took(len(P), diameter_after_adding(self.X, self.block_r, self._n, P, self.p0, self.diameter_mm))
        return self.diameter_mm

    def took(self, k: int, diameter_mm: float) -> None:
        """Count the k points that diameter_after_adding has stored as rows n_points.. of X
        (after reserve(k)), which made the diameter `diameter_mm`."""
        self._n += k
        self.diameter_mm = diameter_mm

    def reserve(self, k: int) -> None:
        """Make room for k more points (the capacity doubles until they fit)."""
        while self._n + k > len(self.X):
            self.X = np.concatenate([self.X, np.empty_like(self.X)])
            self.block_r = np.concatenate([self.block_r, np.zeros_like(self.block_r)])
