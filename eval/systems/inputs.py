"""A closed-loop step's safety.FilterInputs from its joint angles, command, model and
times: the loop's kinematics (monitored points and their Jacobians, the RCM rows) on its
robot. One definition for the loop (eval.systems.filter) and the replay of its compact
log records (eval.log.steps). Units: mm, s, rad; frame W."""
from __future__ import annotations

import numpy as np

from planning.instrument_points import MonitoredPointsConfig, instrument_points
from planning.robot import RCM_GAIN_PER_S, Robot
from safety import FilterConfig, FilterInputs, PointKinematics
from safety.constraints.rcm import displaced, fill_rcm
from safety.filter import rcm_constraint
from safety.margins import conservative_prior


class StepInputs:
    """FilterInputs of the loop's steps on `robot` with the monitored `points`, for a
    filter configured by `filter_config` (its tip speed limit bounds the RCM's drift
    correction: safety.filter.rcm_constraint); `prior` (default: the conservative prior
    about the robot's eye) bounds the motion before the model is trusted and is the
    fallback of untrusted points after."""

    def __init__(self, robot: Robot, points: MonitoredPointsConfig, filter_config: FilterConfig, prior=None):
        self.robot, self.points, self.filter_config = robot, points, filter_config
        self.prior = conservative_prior(robot.scenario.eye_pose.p_WE) if prior is None else prior
        self.lens = robot.scenario.lens_W
        self.set_trocar(robot.p_WC)

    def set_trocar(self, p_WC) -> None:
        """The active trocar p_WC (3,) mm, W: the RCM's and the monitored points' (the loop's, loop_constraints)."""
        self.rcm = rcm_constraint(self.filter_config, p_WC, RCM_GAIN_PER_S)

    def points_at(self, q):
        """planning.instrument_points.InstrumentPoints at joint angles q (6,) rad; ValueError on bad angles."""
        return instrument_points(self.robot, q, self.rcm.p_WC, self.points)

    @staticmethod
    def boundary_count(kind: str | None, n_points: int) -> int:
        """How many of the `n_points` monitored points the filter keeps inside the model: the
        tip and the port against the prior (kind None), all of them against a fitted model."""
        return 2 if kind is None else n_points

    def __call__(self, t_s: float, q, command, shape, kind: str | None, model_time_s: float, sensor_time_s: float,
                 margin_mm: float, trusted, misfit_mm, ip=None, pending=None) -> FilterInputs:
        """The step's inputs: `command` (4,) [v_W mm/s, roll rad/s]; the model's `shape`
        and `kind` (None: the prior alone); the boundary points' `trusted` flags and
        `misfit_mm` (boundary_count of them); `ip` the points at q if known; `pending` (r, 6)
        rad the actuator's pending displacements (None: an ideal actuator), which the RCM
        rows and their planned stop account for as in the loop (safety.constraints.rcm)."""
        robot = self.robot
        ip = self.points_at(q) if ip is None else ip
        k = self.boundary_count(kind, len(ip.names))
        if len(trusted) != k or len(misfit_mm) != k:
            raise ValueError(f"{k} boundary points at these joint angles, but {len(trusted)} trusted flags and "
                             f"{len(misfit_mm)} misfits")
        rcm_A, rcm_b = np.zeros((2, 6)), np.zeros(2)
        pending = None if pending is None else np.ascontiguousarray(pending, dtype=float).reshape(-1, 6)
        R_end, p_end = (ip.R_WI, ip.p_WI) if pending is None or not len(pending) else \
            robot.pose("I", displaced(np.asarray(q, dtype=float), pending))  # the loop's step_pose
        code = fill_rcm(self.rcm.params(), ip.J_C[None], 0, ip.R_WI, ip.p_WI, R_end, p_end,
                        np.zeros((0, 6)) if pending is None else pending, rcm_A, rcm_b, 0)
        return FilterInputs(
            t_s=t_s, q=np.array(q, dtype=float), q_min=robot.q_lower, q_max=robot.q_upper, qdot_max=robot.qdot_max,
            v_cmd_W=np.array(command[:3], dtype=float), J_tip=ip.J_tip,
            boundary_points=[PointKinematics(n, p, J, bool(tr), float(m))
                             for n, p, J, tr, m in zip(ip.names[:k], ip.P_W[:k], ip.J_W[:k], trusted, misfit_mm)],
            model=self.prior if kind is None else shape, model_time_s=model_time_s, sensor_time_s=sensor_time_s,
            rcm_A=rcm_A, rcm_b=rcm_b, lens=self.lens,
            lens_points=[PointKinematics(n, p, J) for n, p, J in zip(ip.lens_names, ip.L_W, ip.J_L)],
            margin_mm=margin_mm, J_roll=ip.J_roll, roll_rate_cmd=float(command[3]),
            fallback=None if kind is None else self.prior, pending=pending,
            rcm_refusal=self.rcm.fault_reason(-code) if code < 0 else "",
        )
