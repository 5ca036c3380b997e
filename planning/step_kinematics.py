"""The instrument's kinematics as the safety filter's loop step reads them: one compiled
call from joint angles to every monitored point, grouped.

Groups (POINT_GROUPS, in this order in P): "tip_port" (the tip, then the cutter port),
"shaft" (the shaft points kept inside the eye), "lens" (the shaft points kept outside
the lens keep-out), "trocar" (the shaft's material point at the trocar, for the RCM).
Units: mm, rad; frame W.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from planning.chain import frame_pose
from planning.instrument_points import MonitoredPointsConfig, instrument_kinematics, kinematics_arguments
from planning.robot import Robot

POINT_GROUPS = ("tip_port", "shaft", "lens", "trocar")
GROUP_CAPACITY = {"tip_port": 2, "shaft": 20, "lens": 64, "trocar": 1}
# params: S (36), R_home_I (9), p_home_I (3), p_WC (3), tip_x, port_I (3), spacing, n_shaft, min depth, lens offsets
_HEAD = 36 + 9 + 3 + 3 + 1 + 3 + 1 + 1 + 1


@njit(cache=True)
def step_kinematics(kp, q):
    """(P (K, 3) mm, J (K, 3, n) mm/rad, ranges (4, 2) int: each group's [start, stop) in
    P, J_tip (3, n), J_roll (1, n) rad/rad, R_WI (3, 3), p_WI (3,) mm, the RCM error mm)
    at q (n,) rad; kp from step_kinematics_params."""
    P, J, k, m, J_roll, err, R_WI, p_WI = instrument_kinematics(
        kp[0:36].reshape((6, 6)), kp[36:45].reshape((3, 3)), kp[45:48], q, kp[48:51], kp[51], kp[52:55], kp[55],
        int(kp[56]), kp[57], kp[_HEAD:])
    ranges = np.empty((4, 2), dtype=np.int64)
    ranges[0, 0], ranges[0, 1] = 0, 2
    ranges[1, 0], ranges[1, 1] = 2, k
    ranges[2, 0], ranges[2, 1] = k, k + m
    ranges[3, 0], ranges[3, 1] = k + m, k + m + 1
    return P, J, ranges, J[0].copy(), J_roll.reshape((1, q.shape[0])), R_WI, p_WI, err


@njit(cache=True)
def step_pose(kp, q):
    """(R_WI (3, 3), p_WI (3,) mm) at q (n,) rad alone, without the points (kp from
    step_kinematics_params): the instrument's pose where the actuator's pending motion
    ends (safety.assembly; Robot.pose("I", q) computes the same)."""
    return frame_pose(kp[0:36].reshape((6, 6)), q, kp[36:45].reshape((3, 3)), kp[45:48])


def step_kinematics_params(robot: Robot, p_WC, config: MonitoredPointsConfig) -> np.ndarray:
    """step_kinematics' kp for this robot, trocar p_WC (3,) mm and monitored points."""
    (S, R_h, p_h), (p_WC, tip_x, port_I, spacing, n_shaft, min_depth, lens) = kinematics_arguments(robot, p_WC, config)
    return np.ascontiguousarray(np.concatenate([
        np.asarray(S, dtype=float).reshape(36), np.asarray(R_h, dtype=float).reshape(9), np.asarray(p_h, dtype=float),
        p_WC, [tip_x], port_I, [spacing, n_shaft, min_depth], lens]), dtype=float)


def point_names(group: str, count: int) -> tuple:
    """The names of a group's first `count` points: "tip", "port"; "shaft<i>"; "lens<i>"; "trocar"."""
    if group == "tip_port":
        return ("tip", "port")[:count]
    if group == "trocar":
        return ("trocar",)[:count]
    return tuple(f"{group}{i}" for i in range(count))
