"""The run record's replay states (eval.systems.step_record): a bounded, regular subsample."""
from __future__ import annotations

import pytest

from eval.systems.step_record import MAX_FILTER_STATES, StepRecord


@pytest.mark.parametrize("offered", [1, MAX_FILTER_STATES, MAX_FILTER_STATES + 1, 1000, 4096])
def test_the_filter_states_kept_are_a_regular_subsample_of_at_most_the_cap(offered):
    rec = StepRecord()
    for i in range(offered):
        rec.keep_filter_state((i,))
    kept = [s[0] for s in rec.filter_states]
    assert 0 < len(kept) <= MAX_FILTER_STATES
    assert kept == list(range(0, offered, rec.filter_stride))  # every stride-th from the first
    assert len(kept) > MAX_FILTER_STATES // 2 or offered <= MAX_FILTER_STATES  # thinned no more than it must
