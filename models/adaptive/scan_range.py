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

    The buffers double without an O(N) copy in one update: once the points fill half the
    capacity, each reserve moves MOVE_PER_POINT rows per point it makes room for (at least
    MIN_MOVE) into a buffer twice as large, which takes over once it holds every point,
    long before the first fills (a point's row and a full block's radius never change
    once written). Copied at once, the doubling at 32,768 points took 0.36-1.0 ms of one
    update (one A-scan period at 2 kHz is 0.5 ms), and it doubles with every doubling.

    State, for models.adaptive.scan_range_kernels.diameter_after_adding: `X` (capacity, 3) the points less
    `p0` (the first point, mm) in its first `n_points` rows, `block_r` the blocks' radii
    (mm), `diameter_mm`.
    """

    MOVE_PER_POINT = 4  # moved from half full, the rows catch up after capacity / 6 more points
    MIN_MOVE = 64

    def __init__(self, capacity: int = 8192):
        capacity = max(SCAN_BLOCK, -(-capacity // SCAN_BLOCK) * SCAN_BLOCK)
        self.X = np.empty((capacity, 3))
        self.block_r = np.zeros(capacity // SCAN_BLOCK)
        self._next: tuple[np.ndarray, np.ndarray] | None = None  # the larger buffers being filled
        self._moved = 0  # rows of X already in the larger buffer
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
        """Make room for k more points: from half full, move rows into buffers twice as
        large (class doc); a batch that would overflow them first finishes the move at once
        (and doubles again until it fits)."""
        n = self._n
        if self._next is None and n + k > len(self.X) // 2:
            self._next = (np.empty((2 * len(self.X), 3)), np.zeros(2 * len(self.block_r)))
            self._moved = 0
        if self._next is not None:
            self._move(n if n + k > len(self.X) else min(n, self._moved + max(self.MIN_MOVE, self.MOVE_PER_POINT * k)))
        while n + k > len(self.X):
            self.X = np.concatenate([self.X, np.empty_like(self.X)])
            self.block_r = np.concatenate([self.block_r, np.zeros_like(self.block_r)])

    def _move(self, upto: int) -> None:
        """Copy rows [moved, upto) and the blocks they complete into the larger buffers; once
        every point is in them (upto == n_points), with the open block's radius, they take over."""
        X, R = self._next
        X[self._moved:upto] = self.X[self._moved:upto]
        R[self._moved // SCAN_BLOCK:upto // SCAN_BLOCK] = self.block_r[self._moved // SCAN_BLOCK:upto // SCAN_BLOCK]
        self._moved = upto
        if upto == self._n:
            if upto % SCAN_BLOCK:
                R[upto // SCAN_BLOCK] = self.block_r[upto // SCAN_BLOCK]
            self.X, self.block_r, self._next = X, R, None
