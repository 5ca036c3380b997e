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


@dataclass
class StepRecord:
    """A run's steps (one Step each: one append per control step) and the states on which
    Drake's diff IK and the filter's compiled step are timed after the run
    (FilterSystem.time_references: (q, command, times, fields, pending, trocar) each)."""

    steps: list = field(default_factory=list)
    drake_diffik_us: list = field(default_factory=list)
    filter_replay_us: list = field(default_factory=list)
    reference_states: list = field(default_factory=list)
