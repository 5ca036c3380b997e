"""Closed-form inverse kinematics of the Meca500 for a shaft line (tip position + direction).

The Meca500 has a spherical wrist: the J4, J5 and J6 axes meet at the J5 origin W5. The
instrument's tip lies on the J6 axis (the flange x axis), so the tip position p_WT and
the shaft direction u_W (from the trocar towards the tip) fix J1..J5 up to eight
branches, and J6 (roll about the shaft) is free. Geometry from shared/reference/facts.md:
shoulder (J2) 135 mm above the base, upper arm 135 mm, forearm 38 mm up and 120 mm along,
W5 -> flange 70 mm, flange -> tip `tip_offset_mm` along the flange x axis.

Used for seeds of the Drake IK (continuity across branches) and for fast reach studies.
All lengths mm, angles rad.
"""
from __future__ import annotations

import numpy as np

SHOULDER_Z_MM = 135.0
UPPER_ARM_MM = 135.0
FOREARM_MM = np.hypot(120.0, 38.0)
FOREARM_ANGLE = np.arctan2(38.0, 120.0)  # forearm's rise above the J4 axis, rad
WRIST_TO_FLANGE_MM = 70.0


def shaft_ik(p_WT, u_W, tip_offset_mm: float, q6: float = 0.0) -> np.ndarray:
    """(K, 6) joint solutions (rad, K = 8 or 0 when out of reach; not filtered by the joint
    limits) that put the tip at p_WT (3,) mm with the flange x axis along the unit u_W
    (3,); J6 = q6. Branches: shoulder (forward / backward) x elbow (either side of the
    stretched arm) x wrist (J5 >= 0 / J5 < 0)."""
    p = np.asarray(p_WT, dtype=float)
    u = np.asarray(u_W, dtype=float)
    w = p - (tip_offset_mm + WRIST_TO_FLANGE_MM) * u  # wrist centre W5
    h = w[2] - SHOULDER_Z_MM
    r = np.hypot(w[0], w[1])
    c = (r * r + h * h - UPPER_ARM_MM**2 - FOREARM_MM**2) / (2.0 * UPPER_ARM_MM * FOREARM_MM)
    if abs(c) > 1.0:
        return np.empty((0, 6))
    q1_front = np.arctan2(w[1], w[0])
    out = []
    # shoulder facing the wrist centre or turned away (J1 + pi, reaching over backwards),
    # elbow on either side of the stretched arm (beta: forearm angle relative to the upper arm)
    for q1, r_s, beta in ((q1_front, r, np.arccos(c)), (q1_front, r, -np.arccos(c)),
                          (q1_front - np.copysign(np.pi, q1_front), -r, np.arccos(c)),
                          (q1_front - np.copysign(np.pi, q1_front), -r, -np.arccos(c))):
        q2 = np.arctan2(r_s, h) - np.arctan2(FOREARM_MM * np.sin(beta), UPPER_ARM_MM + FOREARM_MM * np.cos(beta))
        q3 = beta - np.pi / 2 + FOREARM_ANGLE
        c1, s1, c23, s23 = np.cos(q1), np.sin(q1), np.cos(q2 + q3), np.sin(q2 + q3)
        # shaft direction in the forearm frame: (Rz(q1) Ry(q2 + q3))^T u
        ux, uy = c1 * u[0] + s1 * u[1], -s1 * u[0] + c1 * u[1]
        d = np.array([c23 * ux - s23 * u[2], uy, s23 * ux + c23 * u[2]])
        q5 = np.arctan2(np.hypot(d[1], d[2]), d[0])  # x_F = Rx(q4) Ry(q5) x = (c5, s4 s5, -c4 s5)
        q4 = np.arctan2(d[1], -d[2])
        out.append([q1, q2, q3, q4, q5, q6])
        out.append([q1, q2, q3, q4 - np.pi if q4 > 0 else q4 + np.pi, -q5, q6])
    return np.array(out)
