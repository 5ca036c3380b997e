"""Innovation gate: keep floaters and mis-segmentations out of the eye model."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models._validation import check_count, check_positive


@dataclass(frozen=True)
class OutlierGate:
    """Reject a new point whose distance to the current model exceeds
    max(`min_gate_mm`, `k_residual` x the model's robust residual), once the model rests
    on `min_points` points. The residual is robust (1.4826 x the median absolute distance
    of the last `window` accepted points to the model), so outliers that got in cannot
    open the gate for more. Before the model has `min_points`, and always in addition,
    a point more than `max_jump_mm` from the last accepted one is rejected: A-scans come
    at 2 kHz along a continuous path, so consecutive retinal points lie micrometres to
    tenths of a millimetre apart, while a floater or a wrong peak jumps by millimetres.

    A floater or a wrong peak is an isolated excursion; real retina that the model does
    not fit (a detachment, a staphyloma) keeps arriving. So a run of more than
    `max_consecutive` rejected A-scans (5 ms at 2 kHz by default) is taken as structure
    and accepted: the gate never blinds the model to retina that is really there.
    """

    k_residual: float = 6.0
    min_gate_mm: float = 0.15
    min_points: int = 30
    max_consecutive: int = 10
    window: int = 64
    max_jump_mm: float = 1.0

    def __post_init__(self):
        check_positive(self, "k_residual", "min_gate_mm", "max_jump_mm")
        check_count(self, "min_points", "max_consecutive")
        check_count(self, "window", minimum=1)

    def accept(self, distance_mm, jump_mm, residual_mm: float, n_model_points: int, run: int):
        """(keep flags, new count of consecutive rejections) for points at `distance_mm`
        from a model with robust residual `residual_mm` and `jump_mm` from the previous
        point (sequences of floats, in A-scan order). While more than `max_consecutive`
        far points have come in a row, the gate stays open: that is retina, not a floater."""
        use_model = n_model_points >= self.min_points and residual_mm < float("inf")
        gate = max(self.min_gate_mm, self.k_residual * residual_mm) if use_model else float("inf")
        keep = []
        for d, jump in zip(distance_mm, jump_mm):
            near = jump <= self.max_jump_mm and d <= gate
            run = 0 if near else run + 1
            keep.append(near or run > self.max_consecutive)
        return keep, run
