"""The adaptive model's history (one entry per update) as an append-only sequence that
never copies its old entries when it grows.

A Python list grows by about 1/8 at a time and copies its pointers when it does: in a
stream of single A-scans into one model (the paper's spiral 8 times, 40,744 updates, the
cyclic collector paused) the updates at which the history outgrew its room took 0.33 ms
at 10,661 entries, rising to 1.0 ms at 39,067 (the copy and the fresh pages it touches),
against a median update of 48 us; a 10-minute stream at 2 kHz holds 1.2 million entries.
Here the entries live in blocks of BLOCK: an append touches one block only.
"""
from __future__ import annotations

import operator
from collections.abc import Iterable, Iterator, Sequence
from typing import NamedTuple

import numpy as np

from models.shapes.ellipsoid import Ellipsoid
from models.shapes.sphere import Sphere


class History(Sequence):
    """Entries in the order appended; indexing (negative too) and slicing as a list's
    (a slice is a list); `copy()` shares the entries, which are never changed once made."""

    BLOCK = 4096  # entries per block: a block's own growth copies at most 32 kB of pointers

    __slots__ = ("_blocks", "_n")

    def __init__(self, entries: Iterable = ()):
        self._blocks: list[list] = [[]]
        self._n = 0
        for entry in entries:
            self.append(entry)

    def append(self, entry) -> None:
        last = self._blocks[-1]
        if len(last) == self.BLOCK:
            last = []
            self._blocks.append(last)
        last.append(entry)
        self._n += 1

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(self._n))]
        i = operator.index(index)
        if i < 0:
            i += self._n
        if not 0 <= i < self._n:
            raise IndexError(f"history index {index} out of range for {self._n} entries")
        block, j = divmod(i, self.BLOCK)
        return self._blocks[block][j]

    def __iter__(self) -> Iterator:
        for block in self._blocks:
            yield from block

    def __eq__(self, other) -> bool:
        if not isinstance(other, Sequence) or isinstance(other, (str, bytes)):
            return NotImplemented
        return len(self) == len(other) and all(a == b for a, b in zip(self, other))

    __hash__ = None  # mutable, as a list

    def copy(self) -> History:
        new = History()
        new._blocks = [list(block) for block in self._blocks]
        new._n = self._n
        return new

    def __repr__(self) -> str:
        return f"History({self._n} entries)"


class ModelUpdate(NamedTuple):
    """One entry of the model history (mm, frame of the measured points).

    `n_points`: points in the model; `n_received`: points offered so far, including the
    non-finite and gated ones (so entries can be matched to A-scans);
    `criteria` maps each criterion name to (value, met); `ef_status` is "ok" or why the
    ellipsoid fit failed at this update (the previous good fit is kept). A NamedTuple:
    one is made per A-scan, so it must be cheap.
    """

    n_points: int
    kind: str
    scan_range_mm: float
    sf_residual_mm: float
    ef_residual_mm: float
    axis_change: float
    criteria: dict
    ef_status: str
    sphere_center: np.ndarray | None
    sphere_radius: float
    ellipsoid_center: np.ndarray | None
    ellipsoid_radii: np.ndarray | None
    ellipsoid_rotation: np.ndarray | None
    n_received: int = 0

    @property
    def sphere(self) -> Sphere | None:
        return None if self.sphere_center is None else Sphere(self.sphere_center, self.sphere_radius)

    @property
    def ellipsoid(self) -> Ellipsoid | None:
        if self.ellipsoid_center is None:
            return None
        return Ellipsoid(self.ellipsoid_center, self.ellipsoid_radii, self.ellipsoid_rotation)


__all__ = ["History", "ModelUpdate"]
