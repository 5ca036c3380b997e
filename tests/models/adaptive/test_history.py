"""History: the adaptive model's append-only sequence of update entries, which must read
as the list it replaces, across its blocks."""
from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from models.adaptive.history import History


@pytest.fixture(autouse=True)
def small_blocks(monkeypatch):
    monkeypatch.setattr(History, "BLOCK", 3)  # every test crosses blocks


@given(st.lists(st.integers(), max_size=20), st.integers(-25, 25), st.integers(-25, 25), st.sampled_from([None, 1, 2, -1, -3]))
def test_it_reads_as_the_list_of_its_appends(values, i, j, step):
    h = History()
    for v in values:
        h.append(v)
    assert len(h) == len(values) and list(h) == values and h == values
    assert h[i:j:step] == values[i:j:step]
    if -len(values) <= i < len(values):
        assert h[i] == values[i]
    else:
        with pytest.raises(IndexError):
            h[i]


def test_a_copy_shares_the_entries_but_not_the_appends():
    entry = object()
    h = History([entry, 1, 2, 3])
    c = h.copy()
    c.append(4)
    assert len(h) == 4 and len(c) == 5 and c[0] is entry and h[-1] == 3
    assert History() == [] and History([1]) != [2] and History([1]) != "1"
