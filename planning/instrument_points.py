"""The instrument's monitored points and the RCM rows at one posture, from one evaluation of the chain.

The safety filter keeps a set of material points of the instrument inside the retina
(tip T, cutter port P, points along the shaft inside the eye) and the shaft outside the
lens keep-out, while the shaft pivots about the trocar C. All of them are fixed in the
instrument body I, so one pose and one spatial Jacobian of I give every point's
position and translational Jacobian: J_p = J_v - [r]x J_w with r = p_Wp - p_WI.

Units: mm, rad; Jacobians mm/rad (translational) and rad/rad (roll); frame W.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from planning.chain import frame_pose_and_jacobian, rigid_points
from planning.robot import Robot

_NAMES = ("tip", "port") + tuple(f"shaft{k}" for k in range(20))  # n_shaft <= 20
_LENS_NAMES = tuple(f"lens{k}" for k in range(64))


@dataclass(frozen=True)
class MonitoredPointsConfig:
    """Which shaft points are monitored (mm along the shaft, from the tip backwards).

    `shaft_spacing_mm` x 1..`n_shaft`: retina points behind the tip, kept only when at
    least `min_depth_past_trocar_mm` past the trocar (the shaft crosses the eye wall at
    the trocar, so points next to it cannot keep a clearance from the retina; the convex
    eye wall between them and the tip holds them inside). `lens_offsets_mm`: shaft points
    this far past the trocar (up to the tip) kept outside the lens keep-out.
    """

    shaft_spacing_mm: float = 2.0
    n_shaft: int = 4
    min_depth_past_trocar_mm: float = 3.0
    lens_offsets_mm: tuple = (0.5, 1.5, 3.0, 5.0)

    def __post_init__(self):
        if not (np.isfinite(self.shaft_spacing_mm) and self.shaft_spacing_mm > 0):
            raise ValueError(f"shaft_spacing_mm must be > 0 mm, got {self.shaft_spacing_mm}")
        if not (isinstance(self.n_shaft, int) and 0 <= self.n_shaft <= 20):
            raise ValueError(f"n_shaft must be an int in [0, 20], got {self.n_shaft}")
        if not (np.isfinite(self.min_depth_past_trocar_mm) and self.min_depth_past_trocar_mm >= 0):
            raise ValueError(f"min_depth_past_trocar_mm must be >= 0 mm, got {self.min_depth_past_trocar_mm}")
        if len(self.lens_offsets_mm) > len(_LENS_NAMES):
            raise ValueError(f"lens_offsets_mm takes at most {len(_LENS_NAMES)} offsets, got {len(self.lens_offsets_mm)}")
        if any(not (np.isfinite(o) and o >= 0) for o in self.lens_offsets_mm):
            raise ValueError(f"lens_offsets_mm must be >= 0 mm, got {self.lens_offsets_mm}")


@dataclass(frozen=True, eq=False)
class InstrumentPoints:
    """One posture's kinematics (W, mm, rad).

    `names`, `P_W` (k, 3), `J_W` (k, 3, 6): the points kept inside the retina (first "tip",
    then "port", then "shaft<i>"); `lens_names`, `L_W` (m, 3), `J_L` (m, 3, 6): shaft
    points kept outside the lens; `J_tip` (3, 6); `J_roll` (1, 6): the roll rate about the
    shaft; `R_WI` (3, 3), `p_WI` (3,) mm: the instrument body's pose (x along the shaft,
    towards the tip: `u_W`); `J_C` (3, 6) mm/rad: the Jacobian of the shaft's material
    point at the trocar (the RCM's rows are safety.constraints.RcmEquality's);
    `rcm_error_mm`: the trocar's distance from the shaft axis.
    """

    names: tuple
    P_W: np.ndarray
    J_W: np.ndarray
    lens_names: tuple
    L_W: np.ndarray
    J_L: np.ndarray
    J_tip: np.ndarray
    J_roll: np.ndarray
    R_WI: np.ndarray
    J_C: np.ndarray
    p_WI: np.ndarray
    u_W: np.ndarray
    rcm_error_mm: float


@njit(cache=True)
def instrument_kinematics(S, R_home_I, p_home_I, q, p_WC, tip_x, port_I, shaft_spacing, n_shaft, min_depth, lens_offsets):
    """One posture's monitored points in one compiled pass: (P_W (k + m + 1, 3) mm, J_W
    (k + m + 1, 3, n) mm/rad: tip, port, the k - 2 shaft points kept, the m lens points,
    then the shaft's point at the trocar; k, m; J_roll (n,) rad/rad; the trocar's distance
    from the shaft axis mm; R_WI, p_WI mm). Chain (S, home pose of I) as
    planning.chain; q (n,) rad; p_WC (3,) mm; the rest as MonitoredPointsConfig, mm."""
    R_WI, p_WI, J = frame_pose_and_jacobian(S, q, R_home_I, p_home_I)
    d = np.empty(3)
    lam = 0.0
    for r in range(3):
        d[r] = p_WC[r] - p_WI[r]
        lam += R_WI[r, 0] * d[r]  # the trocar's shaft coordinate, mm
    n_lens = lens_offsets.shape[0]
    x = np.empty(2 + n_shaft + n_lens + 1)
    k = 2
    for i in range(1, n_shaft + 1):
        s = tip_x - i * shaft_spacing
        if s >= lam + min_depth:
            x[k] = s
            k += 1
    m = 0
    for o in lens_offsets:
        if lam + o <= tip_x:
            x[k + m] = lam + o
            m += 1
    P_I = np.zeros((k + m + 1, 3))
    for i in range(2, k + m):
        P_I[i, 0] = x[i]
    P_I[0, 0] = tip_x
    P_I[1, 0], P_I[1, 1], P_I[1, 2] = port_I[0], port_I[1], port_I[2]
    P_I[k + m, 0] = lam
    P_W, J_W = rigid_points(R_WI, p_WI, J, P_I)
    n = q.shape[0]
    J_roll = np.zeros(n)
    err2 = 0.0
    for a in range(2):  # the trocar's offset from the shaft axis along the shaft's lateral directions
        e = R_WI[0, a + 1] * d[0] + R_WI[1, a + 1] * d[1] + R_WI[2, a + 1] * d[2]
        err2 += e * e
    for j in range(n):
        J_roll[j] = R_WI[0, 0] * J[0, j] + R_WI[1, 0] * J[1, j] + R_WI[2, 0] * J[2, j]
    return P_W, J_W, k, m, J_roll, np.sqrt(err2), R_WI, p_WI


def kinematics_arguments(robot: Robot, p_WC, config: MonitoredPointsConfig) -> tuple:
    """instrument_kinematics' arguments but q, in its order around q: (S, R_home_I,
    p_home_I) and (p_WC, tip_x, port_I, spacing, n_shaft, min_depth, lens offsets)."""
    R_h, p_h = robot.chain.homes["I"]
    head = (robot.chain.S, R_h, p_h)
    tail = (np.asarray(p_WC, dtype=float), float(robot.tip_offset_mm), robot.p_IP, float(config.shaft_spacing_mm),
            int(config.n_shaft), float(config.min_depth_past_trocar_mm),
            np.asarray(config.lens_offsets_mm, dtype=float).reshape(-1))
    return head, tail


def instrument_points(robot: Robot, q, p_WC, config: MonitoredPointsConfig = MonitoredPointsConfig()) -> InstrumentPoints:
    """The monitored points, their Jacobians and the shaft's pose at q (6,) rad, trocar p_WC (3,) mm."""
    q = robot.checked_joint_angles(q)
    head, tail = kinematics_arguments(robot, p_WC, config)
    P, J, k, m, J_roll, err, R_WI, p_WI = instrument_kinematics(*head, q, *tail)
    return InstrumentPoints(
        names=_NAMES[:k], P_W=P[:k], J_W=J[:k], lens_names=_LENS_NAMES[:m], L_W=P[k:k + m], J_L=J[k:k + m],
        J_tip=J[0], J_roll=J_roll[None, :], R_WI=R_WI, J_C=J[k + m], p_WI=p_WI, u_W=R_WI[:, 0], rcm_error_mm=float(err),
    )
