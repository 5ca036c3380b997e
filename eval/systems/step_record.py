"""What the loop's filter system records of a run: one Step per control step, and the
states Drake's diff IK and the filter's step are timed on after the run
(eval.systems.filter.FilterSystem). Units: mm, s, rad; frame W."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np


class Step(NamedTuple):
    """One control step's record: time, joints, command and result, what the filter saw
    (mm, s, rad; W). The tip velocity done is J_tip qdot (LoopRun computes it);
    `bounds_mm` (k,) the lower bound on each boundary point's (points_W) true clearance
    that the barrier assumed, h - k sigma - calibration (+inf: none; all +inf at a step refused
    by a fault, whose output carries no clearance; a QP the filter could not solve keeps them)."""

    t: float
    q: np.ndarray
    qdot: np.ndarray
    v_cmd: np.ndarray
    J_tip: np.ndarray
    ok: bool
    reason: str
    intervened: bool
    solve_us: float
    step_us: float
    model_clearance: float
    kind: str
    rcm_error_mm: float
    points_W: np.ndarray
    lens_W: np.ndarray
    bounds_mm: np.ndarray


MAX_FILTER_STATES = 32  # the filter's replay states a run keeps: each holds its step's field params (~1 MB)


@dataclass
class StepRecord:
    """A run's steps (one Step each: one append per control step) and the states on which
    Drake's diff IK ((q, v_cmd) each) and the filter's compiled step ((q, command, times,
    fields, pending, trocar) each) are timed after the run (FilterSystem.time_references).
    The filter's are a regular subsample of at most MAX_FILTER_STATES (keep_filter_state):
    a state holds the field params of its step, which the model remakes every 50 ms, and
    a minute's run would otherwise keep a gigabyte of them."""

    steps: list = field(default_factory=list)
    drake_diffik_us: list = field(default_factory=list)
    filter_replay_us: list = field(default_factory=list)
    diffik_states: list = field(default_factory=list)
    filter_states: list = field(default_factory=list)
    filter_stride: int = 1
    filter_seen: int = 0

    def keep_filter_state(self, state: tuple) -> None:
        """Keep every filter_stride-th state offered; past MAX_FILTER_STATES drop every other
        one kept and double the stride."""
        self.filter_seen += 1
        if (self.filter_seen - 1) % self.filter_stride:
            return
        self.filter_states.append(state)
        if len(self.filter_states) > MAX_FILTER_STATES:
            del self.filter_states[1::2]
            self.filter_stride *= 2
