"""A distance field given by its values at the step's points: what the filter's Python
API hands the compiled step when the caller evaluated the field itself (any shape with
signed_distance and gradient, compiled or not)."""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def tabulated_kernel(fp, P):
    """(h, grad, u) of the M points the table fp = [h (M), grad (3 M), u (M)] was made for;
    NaN when P has another number of points."""
    M = P.shape[0]
    if fp.shape[0] != 5 * M:
        return np.full(M, np.nan), np.full((M, 3), np.nan), np.full(M, np.nan)
    return fp[:M].copy(), fp[M:4 * M].reshape((M, 3)).copy(), fp[4 * M:].copy()


def tabulate(h, grad, u) -> np.ndarray:
    """The table of values h (M,) mm, grad (M, 3), u (M,) mm."""
    return np.ascontiguousarray(np.concatenate([np.asarray(h, dtype=float).reshape(-1),
                                                np.asarray(grad, dtype=float).reshape(-1),
                                                np.asarray(u, dtype=float).reshape(-1)]), dtype=float)
