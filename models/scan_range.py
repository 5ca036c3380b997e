"""Scan range: the largest distance between any two measured points, kept up to date."""
from __future__ import annotations

import math

import numpy as np


class ScanRange:
    """Exact diameter of a growing point set, O(N) vectorised work per new point.

    A new point can only raise the diameter through its distance to the points
    already in; that distance is found with one matrix-vector product
    (|p - q|^2 = |p|^2 + |q|^2 - 2 p.q), in coordinates centred on the first point.
    The triangle bound |p - p0| + max|q - p0| <= diameter skips the product when the
    new point cannot be the end of a new diameter. No O(N^2) work per update.
    """

    def __init__(self, capacity: int = 8192):
        self._X = np.empty((capacity, 3))
        self._sq = np.empty(capacity)
        self._n = 0
        self._p0: np.ndarray | None = None
        self._max_from_p0 = 0.0
        self.diameter_mm = 0.0

    @property
    def n_points(self) -> int:
        return self._n

    def add(self, P: np.ndarray) -> float:
        """Add finite points P (N, 3) mm; return the updated diameter (mm)."""
        for p in P:
            self._add_one(p)
        return self.diameter_mm

    def _add_one(self, p: np.ndarray) -> None:
        if self._p0 is None:
            self._p0 = np.array(p, dtype=float)
        x = p - self._p0
        sq = float(x @ x)
        n = self._n
        r = math.sqrt(sq)
        if n and r + self._max_from_p0 > self.diameter_mm:
            d2 = self._sq[:n] - 2.0 * (self._X[:n] @ x)
            self.diameter_mm = max(self.diameter_mm, math.sqrt(max(float(d2.max()) + sq, 0.0)))
        if n == len(self._X):
            self._X = np.concatenate([self._X, np.empty_like(self._X)])
            self._sq = np.concatenate([self._sq, np.empty_like(self._sq)])
        self._X[n] = x
        self._sq[n] = sq
        self._n = n + 1
        self._max_from_p0 = max(self._max_from_p0, r)
