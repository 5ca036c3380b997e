"""The local retina model's geometry, shared by its compiled kernels (models.local.kernels,
departures, field_kernels): the global quadric's radius along a direction from the model
centre, a node's tangent frame, the z band of a Fibonacci grid's nodes near a direction,
and Wendland's weight. Radii mm, directions unit vectors, angles rad.
"""
from __future__ import annotations

import numpy as np
from numba import njit

N_COV = 21  # the upper triangle of a node's 6 x 6 covariance
N_BASIS = 6  # per node: r(t1, t2) = x0 + x1 t1 + x2 t2 + x3 t1^2 + x4 t1 t2 + x5 t2^2 (gnomonic t, rad)
SPHERE, ELLIPSOID = 1.0, 2.0
GLOBAL_SIZE = 16  # [kind, centre (3), rotation (9, row-major), semi-axes (3)]


@njit(cache=True, inline="always")
def global_radius(c0, gp, u0, u1, u2):
    """Distance (mm) from c0 along the unit direction u to the global quadric gp
    (GLOBAL_SIZE,): NaN when c0 is not inside it."""
    q0, q1, q2 = c0[0] - gp[1], c0[1] - gp[2], c0[2] - gp[3]
    if gp[0] == SPHERE:
        r = gp[13]
        b = u0 * q0 + u1 * q1 + u2 * q2
        c = q0 * q0 + q1 * q1 + q2 * q2 - r * r
        a = 1.0
    else:  # ellipsoid: in its axes, scaled to the unit sphere
        Q0 = (gp[4] * q0 + gp[7] * q1 + gp[10] * q2) / gp[13]
        Q1 = (gp[5] * q0 + gp[8] * q1 + gp[11] * q2) / gp[14]
        Q2 = (gp[6] * q0 + gp[9] * q1 + gp[12] * q2) / gp[15]
        V0 = (gp[4] * u0 + gp[7] * u1 + gp[10] * u2) / gp[13]
        V1 = (gp[5] * u0 + gp[8] * u1 + gp[11] * u2) / gp[14]
        V2 = (gp[6] * u0 + gp[9] * u1 + gp[12] * u2) / gp[15]
        a = V0 * V0 + V1 * V1 + V2 * V2
        b = Q0 * V0 + Q1 * V1 + Q2 * V2
        c = Q0 * Q0 + Q1 * Q1 + Q2 * Q2 - 1.0
    if not c < 0.0:
        return np.nan
    return (-b + np.sqrt(b * b - a * c)) / a


@njit(cache=True, inline="always")
def quadric_taylor(c0, gp, d0, d1, d2, R, m):
    """m (6,) := the quadric gp's radius about c0 near the unit direction d as node d's
    quadratic (models.local.kernels: value mm, slopes mm/rad, curvatures mm/rad^2 in the
    gnomonic coordinates of node_frame(d)), by central differences of 0.02 rad; R a (3, 3)
    workspace."""
    e10, e11, e12, e20, e21, e22 = node_frame(d0, d1, d2)
    h = 0.02
    for i in range(3):
        for j in range(3):
            s1, s2 = (i - 1) * h, (j - 1) * h
            w0, w1, w2 = d0 + s1 * e10 + s2 * e20, d1 + s1 * e11 + s2 * e21, d2 + s1 * e12 + s2 * e22
            s = np.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            R[i, j] = global_radius(c0, gp, w0 / s, w1 / s, w2 / s)
    m[0] = R[1, 1]
    m[1] = (R[2, 1] - R[0, 1]) / (2.0 * h)
    m[2] = (R[1, 2] - R[1, 0]) / (2.0 * h)
    m[3] = (R[2, 1] - 2.0 * R[1, 1] + R[0, 1]) / (2.0 * h * h)
    m[4] = (R[2, 2] - R[2, 0] - R[0, 2] + R[0, 0]) / (4.0 * h * h)
    m[5] = (R[1, 2] - 2.0 * R[1, 1] + R[1, 0]) / (2.0 * h * h)


@njit(cache=True, inline="always")
def node_frame(d0, d1, d2):
    """(e1, e2): an orthonormal tangent frame at the unit direction d (from d alone)."""
    if abs(d2) < 0.9:  # e1 = normalise(z x d)
        a0, a1, a2 = -d1, d0, 0.0
    else:  # e1 = normalise(x x d)
        a0, a1, a2 = 0.0, -d2, d1
    s = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    a0, a1, a2 = a0 / s, a1 / s, a2 / s
    return a0, a1, a2, d1 * a2 - d2 * a1, d2 * a0 - d0 * a2, d0 * a1 - d1 * a0


@njit(cache=True)
def node_frames(dirs):
    """(n, 6): node_frame of every row of dirs (n, 3), e1 then e2 (a table built once per grid)."""
    F = np.empty((dirs.shape[0], 6))
    for k in range(dirs.shape[0]):
        F[k, 0], F[k, 1], F[k, 2], F[k, 3], F[k, 4], F[k, 5] = node_frame(dirs[k, 0], dirs[k, 1], dirs[k, 2])
    return F


@njit(cache=True, inline="always")
def band(n, uz, chord):
    """[k0, k1): the nodes of an n-node Fibonacci sphere whose z lies within chord of uz
    (z = 1 - 2 (k + 1/2) / n falls with k), one more on each side for rounding."""
    k0 = max(int(0.5 * n * (1.0 - (uz + chord)) - 0.5) - 1, 0)
    k1 = min(int(0.5 * n * (1.0 - (uz - chord)) - 0.5) + 2, n)
    return k0, k1


@njit(cache=True, inline="always")
def small_angle(c):
    """The angle (rad) between two unit vectors whose dot product is c: from their chord
    q = sqrt(2 (1 - c)) by 2 asin(q / 2)'s series to q^7 (error under 3e-9 rad for angles
    under 0.3 rad, the supports' and blends' size; a square root where arccos costs
    several times as much in the kernels' inner loops), arccos beyond."""
    q2 = 2.0 * (1.0 - min(c, 1.0))
    if q2 >= 0.09:
        return np.arccos(max(c, -1.0))
    return np.sqrt(q2) * (1.0 + q2 * (1.0 / 24.0 + q2 * (3.0 / 640.0 + q2 * (5.0 / 7168.0))))


@njit(cache=True, inline="always")
def wendland(t):
    """Wendland's C2 function (1 - t)^4 (4 t + 1) for t in [0, 1), 0 beyond (Wendland 1995)."""
    if t >= 1.0:
        return 0.0
    s = 1.0 - t
    return s * s * s * s * (4.0 * t + 1.0)
