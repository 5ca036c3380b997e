"""The QP blocks of the safety filter, one small function per task or constraint.

Decision variable: joint velocities qdot (n,) in rad/s. Jacobians map qdot to point
velocities in W in mm/s (so J is in mm/rad). A control barrier row keeps a value
h(q) >= h_min: dh/dt = grad_h . J qdot >= -gain (h - h_min), with `gain` in 1/s.
"""
from __future__ import annotations

import numpy as np

from safety.qp import Block

# Tip speed polytope: 26 face normals (the cube's faces, edges and corners). With every
# face at distance d, the polytope holds the ball of radius d and lies within the ball
# of radius 1.13 d (maximum over directions, by linear programming); faces at
# v / _POLYTOPE_REACH keep the speed <= v and allow at least 0.87 v in any direction.
_D = np.array([v for v in np.ndindex(3, 3, 3) if v != (1, 1, 1)], dtype=float) - 1.0
_D /= np.linalg.norm(_D, axis=1, keepdims=True)
_POLYTOPE_REACH = 1.15


def tracking(J_tip: np.ndarray, v_cmd: np.ndarray, damping: float, J_roll=None, roll_rate_cmd: float = 0.0) -> Block:
    """Cost |J_tip qdot - v_cmd|^2 (+ |J_roll qdot - roll|^2) + damping |qdot|^2 (mm/s, rad/s)."""
    n = J_tip.shape[1]
    H = J_tip.T @ J_tip + damping * np.eye(n)
    c = -J_tip.T @ v_cmd
    if J_roll is not None:
        Jr = np.atleast_2d(J_roll)
        H = H + Jr.T @ Jr
        c = c - Jr.T @ np.atleast_1d(roll_rate_cmd)
    return Block("tracking", H=2.0 * H, c=2.0 * c)


def barrier(name: str, h: float, grad_W: np.ndarray, J_W: np.ndarray, h_min: float, gain: float,
            max_recovery: float = np.inf) -> Block:
    """Row -(grad . J) qdot <= gain (h - h_min): h (mm) may not fall faster than the barrier
    allows; below h_min it must rise at gain (h_min - h), capped at `max_recovery` mm/s
    (so that a point pushed inside the margin, e.g. by a model update, asks for a
    recovery the speed limits can give instead of making the QP infeasible)."""
    return Block(name, G=-(grad_W @ J_W)[None, :], h=np.array([max(gain * (h - h_min), -max_recovery)]))


def equality(name: str, A: np.ndarray, b: np.ndarray) -> Block:
    """Hard equality rows A qdot = b (the RCM rows, with their drift correction)."""
    return Block(name, A=A, b=b)


def joint_limits(q, q_min, q_max, qdot_max, gain: float, margin_rad: float) -> Block:
    """Bounds: |qdot| <= qdot_max, and the joints approach [q_min + margin, q_max - margin]
    no faster than the barrier rate gain x distance (rad, rad/s, 1/s)."""
    lo = np.maximum(-qdot_max, -gain * (q - (q_min + margin_rad)))
    hi = np.minimum(qdot_max, gain * ((q_max - margin_rad) - q))
    return Block("joint_limits", lb=lo, ub=hi)


def tip_speed(J_tip: np.ndarray, max_speed: float) -> Block:
    """|tip velocity| <= max_speed (mm/s), as 26 half-spaces inside the ball."""
    return Block("tip_speed", G=_D @ J_tip, h=np.full(len(_D), max_speed / _POLYTOPE_REACH))
