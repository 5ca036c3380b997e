"""Closed-form inverse kinematics of the Meca500 for a shaft line (tip position + direction).

The Meca500 has a spherical wrist: the J4, J5 and J6 axes meet at the J5 origin W5. The
instrument's tip lies on the J6 axis (the flange x axis), so the tip position p_WT and
the shaft direction u_W (from the trocar towards the tip) fix J1..J5 up to eight
branches, and J6 (roll about the shaft) is free. The lengths (`ArmLengths`: shoulder
height, upper arm, forearm, W5 -> flange, flange -> tip) are read off the plant's chain
at q = 0 (`arm_lengths`), i.e. the URDF's.

Used for seeds of the Drake IK (continuity across branches) and for fast reach studies.
All lengths mm, angles rad.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

# the joints' axes at q = 0 (J1 .. J6) the closed form is written for
_AXES = np.array([[0, 0, 1], [0, 1, 0], [0, 1, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0]], dtype=float)


class ArmLengths(NamedTuple):
    """The arm's lengths (mm) and the forearm's rise (rad) in the closed form's terms."""

    shoulder_z_mm: float  # J2's axis above the base
    upper_arm_mm: float  # J2 -> J3
    forearm_mm: float  # J3 -> W5, the wrist centre
    forearm_angle_rad: float  # the forearm's rise above the J4 axis
    wrist_to_flange_mm: float  # W5 -> flange, along the flange x axis
    tip_offset_mm: float  # flange -> tip, along the flange x axis


def arm_lengths(chain) -> ArmLengths:
    """The ArmLengths of a planning.chain.Chain at q = 0 (its joints' origins p_WJ and the
    homes of the flange F and tip T). ValueError unless its joints have the Meca500's
    layout: axes z, y, y, x, y, x in W, J1 through W's origin, J2 and J3 above it, the
    J4, J5 and J6 axes meeting at W5 (J5's origin), the flange and tip on the J6 axis
    with the flange's axes along W's."""
    p, (R_F, p_F), (_, p_T) = chain.p_WJ, chain.homes["F"], chain.homes["T"]
    layout = (chain.n == 6 and np.allclose(chain.S[:3].T, _AXES, atol=1e-12) and np.allclose(p[:3, :2], 0.0, atol=1e-9)
              and np.allclose(p[3:, 1:], p[4, 1:], atol=1e-9) and np.allclose(R_F, np.eye(3), atol=1e-12)
              and np.allclose(p_F[1:], p[4, 1:], atol=1e-9) and np.allclose(p_T[1:], p[4, 1:], atol=1e-9))
    if not layout:
        raise ValueError("the closed form needs the Meca500's joint layout (axes z, y, y, x, y, x, spherical wrist)")
    along, rise = p[4, 0] - p[2, 0], p[4, 2] - p[2, 2]  # J3 -> W5
    return ArmLengths(float(p[1, 2]), float(p[2, 2] - p[1, 2]), float(np.hypot(along, rise)),
                      float(np.arctan2(rise, along)), float(p_F[0] - p[4, 0]), float(np.linalg.norm(p_T - p_F)))


def shaft_ik(arm: ArmLengths, p_WT, u_W, q6: float = 0.0) -> np.ndarray:
    """(K, 6) joint solutions (rad, K = 8 or 0 when out of reach; not filtered by the joint
    limits) of the arm with lengths `arm` (Robot.arm) that put the tip at p_WT (3,) mm
    with the flange x axis along the unit u_W (3,); J6 = q6. Branches: shoulder (forward
    / backward) x elbow (either side of the stretched arm) x wrist (J5 >= 0 / J5 < 0)."""
    p = np.asarray(p_WT, dtype=float)
    u = np.asarray(u_W, dtype=float)
    upper, forearm = arm.upper_arm_mm, arm.forearm_mm
    w = p - (arm.tip_offset_mm + arm.wrist_to_flange_mm) * u  # wrist centre W5
    h = w[2] - arm.shoulder_z_mm
    r = np.hypot(w[0], w[1])
    c = (r * r + h * h - upper**2 - forearm**2) / (2.0 * upper * forearm)
    if abs(c) > 1.0:
        return np.empty((0, 6))
    q1_front = np.arctan2(w[1], w[0])
    out = []
    # shoulder facing the wrist centre or turned away (J1 + pi, reaching over backwards),
    # elbow on either side of the stretched arm (beta: forearm angle relative to the upper arm)
    for q1, r_s, beta in ((q1_front, r, np.arccos(c)), (q1_front, r, -np.arccos(c)),
                          (q1_front - np.copysign(np.pi, q1_front), -r, np.arccos(c)),
                          (q1_front - np.copysign(np.pi, q1_front), -r, -np.arccos(c))):
        q2 = np.arctan2(r_s, h) - np.arctan2(forearm * np.sin(beta), upper + forearm * np.cos(beta))
        q3 = beta - np.pi / 2 + arm.forearm_angle_rad
        c1, s1, c23, s23 = np.cos(q1), np.sin(q1), np.cos(q2 + q3), np.sin(q2 + q3)
        # shaft direction in the forearm frame: (Rz(q1) Ry(q2 + q3))^T u
        ux, uy = c1 * u[0] + s1 * u[1], -s1 * u[0] + c1 * u[1]
        d = np.array([c23 * ux - s23 * u[2], uy, s23 * ux + c23 * u[2]])
        q5 = np.arctan2(np.hypot(d[1], d[2]), d[0])  # x_F = Rx(q4) Ry(q5) x = (c5, s4 s5, -c4 s5)
        q4 = np.arctan2(d[1], -d[2])
        out.append([q1, q2, q3, q4, q5, q6])
        out.append([q1, q2, q3, q4 - np.pi if q4 > 0 else q4 + np.pi, -q5, q6])
    return np.array(out)
