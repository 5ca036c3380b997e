"""The safety filter's inputs, configuration and output (mm, s, rad; frame W)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np


@dataclass(frozen=True)
class FilterConfig:
    """Filter parameters (mm, s, rad). `gain_per_s`: barrier rate (gain x dt must stay
    well below 1 at the control rate); `damping`: (mm/rad)^2 weight on |qdot|^2.
    `calibration_bound_mm`, `calibration_bound_deg`: the declared bound of the sensor
    calibration's error (origin mm, beam direction deg; default: 3 standard errors of the
    paper's plate calibration, 250 poses at 20 um noise, models.calibration.uncertainty:
    0.027 mm and 0.125 deg, rounded up); a point measured `calibration_lever_mm` (the
    longest distance the model's points are measured at: the spiral's reach 11.7 mm on
    the emmetropic eye, 13.6 mm on the myopic one, rounded up) from a sensor off by that
    much lies at most `calibration_margin_mm` = mm + lever tan(deg) off, which the
    boundary keeps on top of d_safe."""

    d_safe_mm: float = 0.5
    gain_per_s: float = 20.0
    lens_margin_mm: float = 0.3
    joint_gain_per_s: float = 10.0
    joint_margin_rad: float = np.radians(2.0)
    max_tip_speed_mm_s: float = 20.0
    max_command_speed_mm_s: float = 200.0
    damping: float = 1e-3
    max_model_age_s: float = 0.1
    max_sensor_age_s: float = 0.045  # + a 1 ms control period: a stream fault stops within 46 ms (planning.iioct.stream)
    cutter_clearance_mm: float = 1.0
    max_recovery_mm_s: float = 5.0
    solver: str = "daqp"  # fastest on this QP (bench_safety); "clarabel" also works
    sigma_factor: float = 1.0  # k of the retina barrier's d_safe + k u (u: the field's uncertainty, mm)
    calibration_bound_mm: float = 0.03
    calibration_bound_deg: float = 0.13
    calibration_lever_mm: float = 15.0

    def __post_init__(self):
        for name in ("d_safe_mm", "gain_per_s", "joint_gain_per_s", "max_tip_speed_mm_s", "max_command_speed_mm_s",
                     "max_model_age_s", "max_sensor_age_s", "cutter_clearance_mm", "max_recovery_mm_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"FilterConfig.{name} must be finite and > 0, got {v}")
        for name in ("lens_margin_mm", "joint_margin_rad", "damping", "sigma_factor", "calibration_bound_mm",
                     "calibration_lever_mm"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"FilterConfig.{name} must be finite and >= 0, got {v}")
        if self.solver != "daqp":
            import qpsolvers

            if self.solver not in qpsolvers.available_solvers:
                raise ValueError(f"FilterConfig.solver must be 'daqp' or an installed qpsolvers solver "
                                 f"({', '.join(sorted(qpsolvers.available_solvers))}), got {self.solver!r}")
        if not (np.isfinite(self.calibration_bound_deg) and 0.0 <= self.calibration_bound_deg < 45.0):
            raise ValueError(f"FilterConfig.calibration_bound_deg must be in [0, 45) deg, got {self.calibration_bound_deg}")

    def boundary_mm(self, model_margin_mm: float = 0.0) -> float:
        """The clearance (mm) the retina barrier keeps from a model with margin
        `model_margin_mm` (its uncertainty term): d_safe + that margin + the calibration margin."""
        return self.d_safe_mm + float(model_margin_mm) + self.calibration_margin_mm

    @property
    def barrier_reach_mm(self) -> float:
        """How far past its bound a barrier row can act within a step (mm): what the tip
        speed limit closes at the barrier's rate, max_tip_speed / gain."""
        return self.max_tip_speed_mm_s / self.gain_per_s

    def field_bound(self, fallback) -> tuple:
        """(sigma_factor, fallback Sphere, kept distance mm, reach mm): the barrier's bound on
        a local model's field (models.local.field.LocalField.with_fallback, its params' bound
        block), one definition for the model system that writes it and the filter that reads it."""
        return self.sigma_factor, fallback, self.boundary_mm(), self.barrier_reach_mm

    @property
    def calibration_margin_mm(self) -> float:
        """The declared calibration bound as a clearance (mm): bound mm + lever tan(bound deg)."""
        return self.calibration_bound_mm + self.calibration_lever_mm * float(np.tan(np.radians(self.calibration_bound_deg)))


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
    keep-out; `rcm_A qdot = rcm_b` are the RCM rows (rcm_b their drift correction, which
    a step with no other solution eases: safety.stack); `model` answers signed_distance and
    gradient (> 0 inside); `margin_mm` is added to d_safe (model uncertainty);
    `model_time_s` / `sensor_time_s` are the times of the last model update and sensor
    sample, checked against `t_s`. `fallback` (a shape inside every plausible retina,
    e.g. the conservative prior) bounds the boundary points marked untrusted: their
    clearance is the smaller of the model's and the fallback's. `pending` (r, n) rad: what
    the actuator still carries out if every command from this step on is zero
    (safety.actuator.ActuatorModel.pending_rows); given, the retina barrier is
    actuator-aware (safety.constraints.actuated_barrier); None: an ideal actuator.
    `rcm_refusal`: the planned stop the RCM rows' maker decided for this step
    (safety.constraints.rcm: "actuator cannot hold the trocar"), "" for none.
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
    pending: np.ndarray | None = None
    rcm_refusal: str = ""


class FilterOutput(NamedTuple):
    """`qdot` (n,) rad/s to command (zeros on a fault); `ok` False on a fault, with
    `reason` ("ok" otherwise, or the relaxations the step was solved under: "recovery held",
    "correction eased" or "correction eased, recovery held": safety.stack); `active`: names of the constraints at their bound; `min_clearance_mm`: the
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
