"""RCM-constrained differential kinematics: joint velocities for a commanded tip velocity
that keep the shaft through the trocar (the RCM rows the safety filter reuses)."""
from __future__ import annotations

import numpy as np
from pydrake.multibody.inverse_kinematics import (
    DifferentialInverseKinematicsParameters,
    DoDifferentialInverseKinematics,
)

from planning.robot import MM_PER_M, RCM_GAIN_PER_S, Robot


def rcm_joint_velocity(robot: Robot, q, v_WT_mm_s, p_WC_mm, rcm_gain_per_s: float = RCM_GAIN_PER_S,
                       damping: float = 1e-6) -> np.ndarray:
    """qdot (6,) rad/s minimising |J_T qdot - v|^2 + damping |qdot|^2 subject to the RCM rows
    A qdot = b (robot.rcm_rows, with drift correction): an equality-constrained least
    squares, solved exactly through its KKT system (no QP needed without inequalities)."""
    v = np.asarray(v_WT_mm_s, dtype=float)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"v_WT_mm_s must be a finite (3,) velocity in mm/s, got {v}")
    J = robot.jacobian("T", np.zeros(3), q)
    A, b = robot.rcm_rows(q, p_WC_mm, rcm_gain_per_s)
    H = J.T @ J + damping * np.eye(6)
    K = np.block([[H, A.T], [A, np.zeros((2, 2))]])
    return np.linalg.solve(K, np.concatenate([J.T @ v, b]))[:6]


class DrakeDiffIK:
    """Drake's DoDifferentialInverseKinematics on the robot's plant, for comparison with
    the RCM filter: tip translation only, joint position and speed limits, one control
    step of 1 / rate_hz s. `__call__(q, v_WT_mm_s) -> qdot (6,) rad/s` (NaN when Drake
    reports no solution). It does not hold the RCM: it is the cost reference, not a
    controller of this system."""

    def __init__(self, robot: Robot, rate_hz: float = 1000.0):
        self.robot = robot
        self._context = robot.plant.CreateDefaultContext()
        self._frame = robot.plant.GetFrameByName("tip")
        params = DifferentialInverseKinematicsParameters(6, 6)
        params.set_time_step(1.0 / rate_hz)
        params.set_joint_position_limits((robot.q_lower, robot.q_upper))
        params.set_joint_velocity_limits((-robot.qdot_max, robot.qdot_max))
        params.set_end_effector_velocity_flag([False, False, False, True, True, True])
        self._params = params

    def __call__(self, q, v_WT_mm_s) -> np.ndarray:
        self.robot.plant.SetPositions(self._context, np.asarray(q, dtype=float))
        V = np.concatenate([np.zeros(3), np.asarray(v_WT_mm_s, dtype=float) / MM_PER_M])
        result = DoDifferentialInverseKinematics(self.robot.plant, self._context, V, self._frame, self._params)
        return result.joint_velocities if result.joint_velocities is not None else np.full(6, np.nan)
