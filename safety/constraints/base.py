"""What a constraint of the safety filter is: a small object that fills rows of the QP.

The filter's decision variable is the joint velocity qdot (n,) rad/s. A constraint is
one of three kinds:

- "inequality": rows G qdot <= h (a barrier, a speed polytope);
- "equality": rows A qdot = b (the remote centre of motion);
- "bounds": elementwise lb <= qdot <= ub, intersected with every other bound.

Each constraint names a module-level compiled function, its *filler*, that writes its
rows into the step's workspace, and gives the filler its parameters as one float array
(`params()`, mm, s, rad). The filler declares what it reads by its argument names (the
step's context, listed in CONTEXT); the filter assembles its compiled step from the
fillers of the constraints it is given, once, at construction (safety.assembly), so the
rule a constraint states is written once and runs the same in every path.

A constraint that watches points reads one *group* of the step's points (for example
the tip and the cutter port, the shaft, the shaft's lens points) and, if it keeps them
away from something, one *field* slot (a distance field: the eye model, the lens):
the filter evaluates the field at the group's points and hands the filler the signed
distance, its gradient and its uncertainty there.
"""
from __future__ import annotations

from typing import ClassVar

import numpy as np

KINDS = ("inequality", "equality", "bounds")

# the names a filler's arguments may take, and what the assembled step passes for each
CONTEXT = {
    "sp": "the constraint's params() (float64 (k,))",
    "q": "joint angles (n,) rad",
    "command": "the command (4,): tip velocity (3,) mm/s in W, roll rate rad/s",
    "J_tip": "the tip's translational Jacobian (3, n) mm/rad (the tracking cost's)",
    "P": "every point of the step (K, 3) mm, W",
    "J": "their translational Jacobians (K, 3, n) mm/rad",
    "start": "first index of the constraint's group in P",
    "stop": "one past its last index",
    "R_WI": "the instrument body's rotation (3, 3) in W (its x axis along the shaft)",
    "p_WI": "the instrument body's origin (3,) mm in W",
    "R_WI_end": "R_WI once the actuator has carried out `pending` (the kinematics at q + the rows' sum; R_WI: none)",
    "p_WI_end": "p_WI there, mm",
    "fh": "the field's signed distance (stop - start,) mm at the group's points, > 0 inside",
    "fg": "its unit gradient (stop - start, 3)",
    "fu": "its uncertainty (stop - start,) mm",
    "G": "inequality rows (capacity, n), written from row m on",
    "h": "their right-hand sides (capacity,)",
    "ids": "their identities (capacity,) int: id0 + the row's index within the constraint",
    "m": "rows of G written so far (an inequality filler returns the new count)",
    "id0": "the constraint's first row identity",
    "A": "equality rows (capacity, n), written from row p on",
    "b": "their right-hand sides",
    "p": "equality rows written so far (an equality filler returns the new count)",
    "lb": "lower bounds (n,) rad/s, to tighten (never to loosen)",
    "ub": "upper bounds (n,) rad/s",
    "point_h": "per-point clearance (K,) mm a barrier reports (+inf: none)",
    "point_bound": "per-point lower bound (K,) mm on the TRUE clearance that a barrier's rule assumes, "
                   "h - k u - calibration (+inf: none): the truth below it breaks the rule's premise",
    "pending": "joint displacements (r, n) rad the actuator still carries out if every command from this step on is "
               "zero, rows whose contributions each grow from 0 to full (safety.actuator.ActuatorModel.pending_rows; "
               "r = 0: not modelled)",
}


class Constraint:
    """Base of the filter's constraints. A subclass sets `kind` and `filler`, and gives
    `name`, `params()` and, for an inequality, `max_rows(group_size)`. `group`: the point
    group it reads (None: none); `field`: the field slot it keeps its points from (None:
    none); `intervenes`: a row of it at its bound means the filter changed the command;
    `reports_clearance`: its points' field distances count as the boundary's clearance;
    `drift_correction`: an equality whose right-hand side corrects a drift, which a step
    with no other solution may scale down (safety.stack: correction eased)."""

    kind: ClassVar[str] = "inequality"
    filler: ClassVar[object] = None
    group: str | None = None
    field: str | None = None
    intervenes: bool = True
    reports_clearance: bool = False
    drift_correction: bool = False

    name: str

    def params(self) -> np.ndarray:
        """The filler's `sp`: a C-contiguous float64 array."""
        return np.zeros(0)

    def max_rows(self, group_size: int) -> int:
        """The most rows of G (inequality) or A (equality) it writes for a group of that size."""
        return 0

    def row_name(self, index: int, point_names: tuple) -> str:
        """The name of its row `index` (a point's row: "<name>:<point>")."""
        if self.group is not None and index < len(point_names):
            return f"{self.name}:{point_names[index]}"
        return self.name

    def fault_reason(self, code: int) -> str:
        """Why its filler refused the step (it returned the negative `code`)."""
        return f"{self.name}: fault {code}"

    def key(self) -> tuple:
        """What the assembled step depends on (not the parameter values): also whether its
        equality rows are a drift correction (the stack's relaxed forms read it)."""
        return (type(self).__module__, type(self).__qualname__, self.kind, self.group, self.field,
                bool(self.drift_correction))


def as_params(*parts) -> np.ndarray:
    """One C-contiguous, writeable float64 array of the parts, flattened in order."""
    return np.ascontiguousarray(np.concatenate([np.asarray(p, dtype=float).reshape(-1) for p in parts]), dtype=float)


def check_finite_positive(owner: str, allow_zero: bool = False, **values) -> None:
    """ValueError naming `owner.field` unless every value is finite and > 0 (>= 0)."""
    for name, v in values.items():
        ok = np.isfinite(v) and (v >= 0 if allow_zero else v > 0)
        if not ok:
            raise ValueError(f"{owner}.{name} must be finite and {'>=' if allow_zero else '>'} 0, got {v}")
