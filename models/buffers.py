"""Growing the stores of streamed points: one rule for every model part that keeps them.

A store holds its rows in arrays with room to spare; `grown` gives arrays with room for
`needed` rows (at least twice the old capacity, so a stream of single A-scans copies each
row O(1) times on average; at most `limit`), the first `kept` rows of each copied."""
from __future__ import annotations

import numpy as np


def grown(kept: int, needed: int, *arrays: np.ndarray, limit: int | None = None) -> tuple[np.ndarray, ...]:
    """New arrays of max(needed, 2 x the old length) rows (at most `limit`; the rest of
    each array's shape and its dtype kept), each holding its old array's first `kept` rows."""
    size = max(int(needed), 2 * len(arrays[0]))
    if limit is not None:
        size = min(size, int(limit))
    out = []
    for a in arrays:
        new = np.empty((size, *a.shape[1:]), dtype=a.dtype)
        new[:kept] = a[:kept]
        out.append(new)
    return tuple(out)


__all__ = ["grown"]
