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

from planning.chain import rigid_points
from planning.robot import RCM_GAIN_PER_S, Robot

PORT_I_MM = np.array([91.7, -0.25, 0.0])  # cutter port in I (meca500.urdf "port_frame")
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
    shaft; `rcm_A` (2, 6), `rcm_b` (2,) mm/s: the RCM rows (Robot.rcm_rows);
    `p_WI`, `u_W`: the shaft axis; `rcm_error_mm`: the trocar's distance from it.
    """

    names: tuple
    P_W: np.ndarray
    J_W: np.ndarray
    lens_names: tuple
    L_W: np.ndarray
    J_L: np.ndarray
    J_tip: np.ndarray
    J_roll: np.ndarray
    rcm_A: np.ndarray
    rcm_b: np.ndarray
    p_WI: np.ndarray
    u_W: np.ndarray
    rcm_error_mm: float


def instrument_points(robot: Robot, q, p_WC, config: MonitoredPointsConfig = MonitoredPointsConfig(),
                      rcm_gain_per_s: float = RCM_GAIN_PER_S) -> InstrumentPoints:
    """The monitored points, their Jacobians and the RCM rows at q (6,) rad, trocar p_WC (3,) mm."""
    R_WI, p_WI, J = robot.pose_and_spatial_jacobian("I", q)
    u = R_WI[:, 0]
    tip_x = robot.tip_offset_mm
    d = np.asarray(p_WC, dtype=float) - p_WI
    lam = float(u @ d)  # the trocar's shaft coordinate, mm
    shaft_x = [tip_x - k * config.shaft_spacing_mm for k in range(1, config.n_shaft + 1)]
    shaft_x = [x for x in shaft_x if x >= lam + config.min_depth_past_trocar_mm]
    lens_x = [lam + o for o in config.lens_offsets_mm if lam + o <= tip_x]
    k, m = 2 + len(shaft_x), len(lens_x)
    names = _NAMES[:k]
    lens_names = _LENS_NAMES[:m]
    P_I = np.zeros((k + m + 1, 3))  # tip, port, shaft points, lens points, the trocar's shaft point
    P_I[:, 0] = [tip_x, 0.0, *shaft_x, *lens_x, lam]
    P_I[1] = PORT_I_MM
    P_all, J_all = rigid_points(R_WI, p_WI, J, P_I)
    P_W, J_W, L_W, J_L, J_Q = P_all[:k], J_all[:k], P_all[k:k + m], J_all[k:k + m], J_all[-1]
    N = R_WI[:, 1:].T  # the shaft's two lateral directions
    e = N @ d
    return InstrumentPoints(
        names=names, P_W=P_W, J_W=J_W, lens_names=lens_names, L_W=L_W, J_L=J_L,
        J_tip=J_W[0], J_roll=(u @ J[:3])[None, :], rcm_A=N @ J_Q, rcm_b=rcm_gain_per_s * e,
        p_WI=p_WI, u_W=u, rcm_error_mm=float(np.linalg.norm(e)),
    )
