"""Innovation gate: keep floaters and mis-segmentations out of the eye model.

`OutlierGate` is the configuration (and the decision rule); `GateState` is one model's
running state: the last accepted point, the recent distances and steps behind the
robust residual and the jump limit, the run of consecutive rejections, and the counters.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from models.adaptive.gate_kernels import G_N_REJECTED, RESIDUAL_REFRESH, gate_points
from models.fit.ellipsoid_fit import LENGTH_SCALE_MM
from models.shapes.validation import check_count, check_positive

__all__ = ["RESIDUAL_REFRESH", "GateState", "OutlierGate"]  # RESIDUAL_REFRESH: the gate's, defined with its kernel


@dataclass(frozen=True)
class OutlierGate:
    """Reject a new point whose distance to the current model exceeds
    max(`min_gate_mm`, `k_residual` x the model's robust residual), once the model rests
    on `min_points` points. The residual is robust (1.4826 x the median absolute distance
    of the last `window` accepted points to the model), so outliers that got in cannot
    open the gate for more.

    Before the model has `min_points`, and always in addition, a point that jumps from
    the last accepted one by more than the jump limit is rejected: A-scans come along a
    continuous path, so consecutive retinal points lie a step apart (the loop's 2 kHz
    scan: ~20 um; the paper's spiral: ~0.16 mm), while a floater lies at least 0.5 mm in
    front of the retina along its beam. The jump limit is `k_residual` x the median step
    between consecutive accepted points of the last `window`, at least `min_gate_mm`
    (two A-scans' 20 um distance noises differ by 28 um SD: 0.15 mm is 5 of them) and at
    most `max_jump_mm` (the limit before a step is known): 0.15 mm in the loop, where a
    1 mm limit let floaters 0.5-1 mm short of the retina in while the early sphere's
    gate was wide; 0.97-1 mm on the paper's spiral.
    The very first point has no accepted one to be compared with: it is held back until
    the next one lies within `max_jump_mm` of it, then both are kept (otherwise it is
    rejected and the next one waits in its place). Taken unchecked, a floater on the
    first A-scan (one scan in twenty at a 5 % floater rate) got into the model and, as
    the reference, pushed the next ten retinal points out; in the loop's least-squares
    ellipsoid that one point 6.6 mm off outweighed 20,000 retinal points (EF MAE 226 um
    against 39 um).

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


class GateState:
    """One model's gate: `admit(P, quadric, p0, n_model_points)` returns the points of P
    (N, 3) mm to keep (preceded by the gate's first point, held back since an earlier
    call, when P's first point confirms it) and counts the others in `n_rejected`.
    `quadric` (10,) is the current model in the fits' scaled coordinates about `p0`
    (None before a model exists).

    The state lives in arrays that the compiled gate (models.adaptive.gate_kernels.gate_points)
    updates in place, so that the per-A-scan update can run it inside one compiled call:
    `params` the gate's numbers, `counts` its counters (indices G_* of models.adaptive.gate_kernels),
    `last` the last kept point (mm; before any, the pending first point), `scales` (2,)
    the robust residual and the jump limit (mm), `recent` (2, window) the distances to
    the model and the steps (mm) of the last `window` accepted points.
    """

    def __init__(self, gate: OutlierGate):
        self.gate = gate
        self.params = np.array([gate.k_residual, gate.min_gate_mm, gate.min_points, gate.max_consecutive,
                                gate.max_jump_mm], dtype=float)
        self.counts = np.zeros(5, dtype=np.int64)
        self.last = np.zeros(3)
        self.scales = np.array([np.inf, gate.max_jump_mm])
        self.recent = np.empty((2, gate.window))

    @property
    def n_rejected(self) -> int:
        return int(self.counts[G_N_REJECTED])

    def admit(self, P: np.ndarray, quadric, p0, n_model_points: int) -> np.ndarray:
        if len(P) == 0:
            return P
        keep = np.empty(len(P), dtype=bool)
        has_quadric = quadric is not None
        pending = self.last.copy()
        n_kept, took_pending = gate_points(P, keep, quadric if has_quadric else _NO_QUADRIC, has_quadric,
                                           _NO_ORIGIN if p0 is None else p0, LENGTH_SCALE_MM, n_model_points,
                                           self.params, self.counts, self.last, self.scales, self.recent)
        kept = P if n_kept == len(P) else P[keep]
        return np.vstack([pending, kept]) if took_pending else kept


_NO_QUADRIC = np.zeros(10)  # stands for "no model yet" in the compiled gate (its distances are then 0)
_NO_ORIGIN = np.zeros(3)
