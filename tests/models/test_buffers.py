"""models.buffers.grown: the stores' growth rule."""
import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from models.buffers import grown


@given(st.integers(1, 50), st.integers(0, 50), st.integers(0, 200), st.one_of(st.none(), st.integers(1, 300)))
def test_grown_keeps_rows_and_makes_room(length, kept, needed, limit):
    kept = min(kept, length)
    limit = None if limit is None else max(limit, length)  # a store is never longer than its limit
    X = np.arange(3.0 * length).reshape(length, 3)
    w = np.arange(length, dtype=np.int64)
    X2, w2 = grown(kept, needed, X, w, limit=limit)
    size = max(needed, 2 * length) if limit is None else min(max(needed, 2 * length), limit)
    assert X2.shape == (size, 3) and w2.shape == (size,) and w2.dtype == np.int64
    np.testing.assert_array_equal(X2[:kept], X[:kept])
    np.testing.assert_array_equal(w2[:kept], w[:kept])
    assert X2 is not X and not np.shares_memory(X2, X)


def test_single_rows_copy_each_row_a_bounded_number_of_times():
    # a stream of single rows: at least doubling, so the rows copied stay under 2 x the rows stored
    X, n, copied = np.empty((1, 3)), 0, 0
    for _ in range(10_000):
        if n + 1 > len(X):
            copied += n
            X, = grown(n, n + 1, X)
        X[n] = n
        n += 1
    assert copied < 2 * n
    np.testing.assert_array_equal(X[:n, 0], np.arange(n))
