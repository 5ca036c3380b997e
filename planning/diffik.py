"""RCM-constrained differential kinematics: joint velocities for a commanded tip velocity
that keep the shaft through the trocar (the RCM rows the safety filter reuses)."""
from __future__ import annotations

import numpy as np

from planning.robot import RCM_GAIN_PER_S, Robot


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
