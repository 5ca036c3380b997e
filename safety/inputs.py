"""The safety filter's inputs, configuration and output (mm, s, rad; frame W)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np


@dataclass(frozen=True)
class FilterConfig:
    """Filter parameters (mm, s, rad). `gain_per_s`: barrier rate (gain x dt must stay
    well below 1 at the control rate); `damping`: (mm/rad)^2 weight on |qdot|^2."""

    d_safe_mm: float = 0.5
    gain_per_s: float = 20.0
    lens_margin_mm: float = 0.3
    joint_gain_per_s: float = 10.0
    joint_margin_rad: float = np.radians(2.0)
    max_tip_speed_mm_s: float = 20.0
    max_command_speed_mm_s: float = 200.0
    damping: float = 1e-3
    max_model_age_s: float = 0.1
    max_sensor_age_s: float = 0.05
    cutter_clearance_mm: float = 1.0
    max_recovery_mm_s: float = 5.0
    solver: str = "daqp"  # fastest on this QP (bench_safety); "clarabel" also works
    sigma_factor: float = 1.0  # k of the retina barrier's d_safe + k u (u: the field's uncertainty, mm)

    def __post_init__(self):
        for name in ("d_safe_mm", "gain_per_s", "joint_gain_per_s", "max_tip_speed_mm_s", "max_command_speed_mm_s",
                     "max_model_age_s", "max_sensor_age_s", "cutter_clearance_mm", "max_recovery_mm_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"FilterConfig.{name} must be finite and > 0, got {v}")
        for name in ("lens_margin_mm", "joint_margin_rad", "damping", "sigma_factor"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"FilterConfig.{name} must be finite and >= 0, got {v}")


@dataclass(frozen=True, eq=False)
class PointKinematics:
    """A monitored point: name, position p_W (3,) mm, translational Jacobian J_W (3, n)
    mm/rad; `trusted` False where the model has no data near the point (then the
    inputs' `fallback` shape bounds it too); `margin_mm` extra clearance for this point
    (e.g. the model's measured local misfit near it)."""

    name: str
    p_W: np.ndarray
    J_W: np.ndarray
    trusted: bool = True
    margin_mm: float = 0.0


@dataclass(frozen=True, eq=False)
class FilterInputs:
    """One control step's inputs (mm, s, rad; W frame).

    `boundary_points` must stay inside the retina model, `lens_points` outside the lens
    keep-out; `rcm_A qdot = rcm_b` are the RCM rows; `model` answers signed_distance and
    gradient (> 0 inside); `margin_mm` is added to d_safe (model uncertainty);
    `model_time_s` / `sensor_time_s` are the times of the last model update and sensor
    sample, checked against `t_s`. `fallback` (a shape inside every plausible retina,
    e.g. the conservative prior) bounds the boundary points marked untrusted: their
    clearance is the smaller of the model's and the fallback's.
    """

    t_s: float
    q: np.ndarray
    q_min: np.ndarray
    q_max: np.ndarray
    qdot_max: np.ndarray
    v_cmd_W: np.ndarray
    J_tip: np.ndarray
    boundary_points: list
    model: object
    model_time_s: float
    sensor_time_s: float
    rcm_A: np.ndarray | None = None
    rcm_b: np.ndarray | None = None
    lens: object = None
    lens_points: list = field(default_factory=list)
    margin_mm: float = 0.0
    J_roll: np.ndarray | None = None
    roll_rate_cmd: float = 0.0
    fallback: object = None


class FilterOutput(NamedTuple):
    """`qdot` (n,) rad/s to command (zeros on a fault); `ok` False on a fault, with
    `reason`; `active`: names of the constraints at their bound; `min_clearance_mm`: the
    smallest model clearance of the boundary points minus d_safe-free (mm);
    `cutter_allowed`: the port's clearance exceeds the interlock threshold;
    `intervened`: the output departs from the command (an active constraint, or a tip
    velocity off the command by more than 1 %). A NamedTuple: one is made per control
    step, so it must be cheap."""

    qdot: np.ndarray
    ok: bool
    reason: str
    active: tuple = ()
    min_clearance_mm: float = float("nan")
    cutter_allowed: bool = False
    intervened: bool = True
    solve_us: float = 0.0
