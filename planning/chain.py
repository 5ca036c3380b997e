"""Compiled forward kinematics of the arm, read off its Drake MultibodyPlant.

The 1 kHz loop asks for a few frame poses and Jacobians per step. Drake answers each
in 10-50 us from Python (SetPositions, CalcPoseInWorld, the Jacobian calls and their
argument conversions); the arithmetic is well under a microsecond. So the chain is
generated from the plant once, as a product of exponentials (Lynch & Park, Modern
Robotics, ch. 4): each revolute joint's screw axis in W at q = 0 (its axis and its
frame's origin there) and each frame's home pose, the plant's (hence the URDF's) only,
and evaluated by one compiled call.

    X_WB(q) = exp([S_1] q_1) ... exp([S_6] q_6) X_WB(0)
    J_s(q)  = [Ad_{e_1..e_{i-1}} S_i]_i   (space Jacobian: twists about W's origin)

Tests hold it to the plant's own answers. Units: mm, rad; twists (omega rad/rad,
v mm/rad); frame W.
"""
from __future__ import annotations

import numba
import numpy as np
from pydrake.multibody.tree import RevoluteJoint

MM_PER_M = 1000.0


@numba.njit(cache=True, inline="always")
def _times_joint(S, i, th, R, p, work):
    """(R, p) <- (R, p) exp([S_i] th), in place: the product so far times joint i's
    exponential at th rad (work: (2, 3, 3) scratch). Written out in scalars: for
    3-vectors a BLAS call costs more than its work (and R's row in locals, updated in
    place, runs faster than through a third scratch matrix)."""
    Ri, G = work[0], work[1]
    wx, wy, wz = S[0, i], S[1, i], S[2, i]
    c, s = np.cos(th), np.sin(th)
    W = ((0.0, -wz, wy), (wz, 0.0, -wx), (-wy, wx, 0.0))
    for r in range(3):  # Rodrigues: R_i = I + s W + (1 - c) W^2; G = th I + (1 - c) W + (th - s) W^2
        for k in range(3):
            w2 = W[r][0] * W[0][k] + W[r][1] * W[1][k] + W[r][2] * W[2][k]
            e = 1.0 if r == k else 0.0
            Ri[r, k] = e + s * W[r][k] + (1.0 - c) * w2
            G[r, k] = th * e + (1.0 - c) * W[r][k] + (th - s) * w2
    # the exponential's translation t = G v; then p += R t and R = R R_i
    tx = G[0, 0] * S[3, i] + G[0, 1] * S[4, i] + G[0, 2] * S[5, i]
    ty = G[1, 0] * S[3, i] + G[1, 1] * S[4, i] + G[1, 2] * S[5, i]
    tz = G[2, 0] * S[3, i] + G[2, 1] * S[4, i] + G[2, 2] * S[5, i]
    for r in range(3):
        a, b, c = R[r, 0], R[r, 1], R[r, 2]
        p[r] += a * tx + b * ty + c * tz
        for k in range(3):
            R[r, k] = a * Ri[0, k] + b * Ri[1, k] + c * Ri[2, k]


@numba.njit(cache=True)
def chain_kinematics(S, q):
    """(R (3, 3), p (3,) mm, J_s (6, n)) of the chain at q: the product of the
    exponentials (applied to a home pose X_WB(0) it gives X_WB(q)) and the space
    Jacobian, rows 0-2 angular, 3-5 the velocity of the point at W's origin."""
    n = S.shape[1]
    R = np.eye(3)
    p = np.zeros(3)
    J = np.empty((6, n))
    work = np.empty((2, 3, 3))
    for i in range(n):
        for r in range(3):  # the twist moved by the product so far: (R w, R v + p x R w)
            J[r, i] = R[r, 0] * S[0, i] + R[r, 1] * S[1, i] + R[r, 2] * S[2, i]
            J[3 + r, i] = R[r, 0] * S[3, i] + R[r, 1] * S[4, i] + R[r, 2] * S[5, i]
        J[3, i] += p[1] * J[2, i] - p[2] * J[1, i]
        J[4, i] += p[2] * J[0, i] - p[0] * J[2, i]
        J[5, i] += p[0] * J[1, i] - p[1] * J[0, i]
        _times_joint(S, i, q[i], R, p, work)
    return R, p, J


@numba.njit(cache=True)
def chain_pose_into(S, q, R, p, work):
    """(R (3, 3), p (3,) mm) <- the product of the exponentials at q, in place:
    chain_kinematics's R and p bit for bit, without its Jacobian or any allocation
    (work: (2, 3, 3) scratch), for callers that evaluate the chain in a loop."""
    for r in range(3):
        p[r] = 0.0
        for k in range(3):
            R[r, k] = 1.0 if r == k else 0.0
    for i in range(S.shape[1]):
        _times_joint(S, i, q[i], R, p, work)


@numba.njit(cache=True, inline="always")
def _rotated(R, v0, v1, v2, r):
    """Row r of R (v0, v1, v2)."""
    return R[r, 0] * v0 + R[r, 1] * v1 + R[r, 2] * v2


@numba.njit(cache=True)
def _apply(R, p, R_home, p_home):
    """(R R_home, R p_home + p)."""
    R_WF = np.empty((3, 3))
    p_WF = p.copy()
    for r in range(3):
        for k in range(3):
            R_WF[r, k] = _rotated(R, R_home[0, k], R_home[1, k], R_home[2, k], r)
        p_WF[r] += _rotated(R, p_home[0], p_home[1], p_home[2], r)
    return R_WF, p_WF


@numba.njit(cache=True)
def frame_axis_into(R, p, R_home, p_home, axis, O, U, m):
    """O[m], U[m] <- the origin (mm) and axis `axis` (0 x, 1 y, 2 z) in W of the frame
    with home pose (R_home, p_home) on the product (R, p) of the exponentials
    (chain_pose_into): that column of `_apply`'s pose, by the same arithmetic."""
    for r in range(3):
        U[m, r] = _rotated(R, R_home[0, axis], R_home[1, axis], R_home[2, axis], r)
        O[m, r] = p[r] + _rotated(R, p_home[0], p_home[1], p_home[2], r)


@numba.njit(cache=True)
def frame_pose(S, q, R_home, p_home):
    """(R_WF (3, 3), p_WF (3,) mm) of a frame with home pose (R_home, p_home) at q = 0."""
    R, p = _chain_pose(S, q)
    return _apply(R, p, R_home, p_home)


@numba.njit(cache=True)
def frame_position(S, q, R_home, p_home):
    """p_WF (3,) mm: frame_pose's position alone, bit for bit (the control loop's tip
    position for its command source, every step)."""
    return frame_pose(S, q, R_home, p_home)[1]


@numba.njit(cache=True)
def _chain_pose(S, q):
    """(R (3, 3), p (3,) mm) of the product of the exponentials at q (chain_pose_into)."""
    R, p = np.empty((3, 3)), np.empty(3)
    chain_pose_into(S, q, R, p, np.empty((2, 3, 3)))
    return R, p


@numba.njit(cache=True)
def frame_pose_and_jacobian(S, q, R_home, p_home):
    """(R_WF, p_WF mm, J (6, n)): the frame's pose and the spatial Jacobian of its origin
    (rows 0-2 angular rad/rad, 3-5 translational mm/rad), in W."""
    R, p, J = chain_kinematics(S, q)
    R_WF, p_WF = _apply(R, p, R_home, p_home)
    for i in range(J.shape[1]):  # shift the twists from W's origin to the frame's: v += w x p_WF
        J[3, i] += J[1, i] * p_WF[2] - J[2, i] * p_WF[1]
        J[4, i] += J[2, i] * p_WF[0] - J[0, i] * p_WF[2]
        J[5, i] += J[0, i] * p_WF[1] - J[1, i] * p_WF[0]
    return R_WF, p_WF, J


@numba.njit(cache=True)
def rigid_points(R_WF, p_WF, J_F, P_F):
    """(P_W (k, 3) mm, J_W (k, 3, n) mm/rad) of points P_F (k, 3) mm fixed in a frame with
    pose (R_WF, p_WF) and origin spatial Jacobian J_F (6, n): J_v - [r]x J_w, r = R_WF p."""
    k, n = P_F.shape[0], J_F.shape[1]
    P_W = np.empty((k, 3))
    J_W = np.empty((k, 3, n))
    for m in range(k):
        r0 = R_WF[0, 0] * P_F[m, 0] + R_WF[0, 1] * P_F[m, 1] + R_WF[0, 2] * P_F[m, 2]
        r1 = R_WF[1, 0] * P_F[m, 0] + R_WF[1, 1] * P_F[m, 1] + R_WF[1, 2] * P_F[m, 2]
        r2 = R_WF[2, 0] * P_F[m, 0] + R_WF[2, 1] * P_F[m, 1] + R_WF[2, 2] * P_F[m, 2]
        P_W[m, 0], P_W[m, 1], P_W[m, 2] = p_WF[0] + r0, p_WF[1] + r1, p_WF[2] + r2
        for j in range(n):  # v_p = v + w x r
            w0, w1, w2 = J_F[0, j], J_F[1, j], J_F[2, j]
            J_W[m, 0, j] = J_F[3, j] + w1 * r2 - w2 * r1
            J_W[m, 1, j] = J_F[4, j] + w2 * r0 - w0 * r2
            J_W[m, 2, j] = J_F[5, j] + w0 * r1 - w1 * r0
    return P_W, J_W


class Chain:
    """The plant's serial chain of revolute joints with the home poses of `frames`.

    `S` (6, n): screw axes in W at q = 0 (angular; linear at W's origin, mm/rad);
    `p_WJ` (n, 3) mm: the joints' frame origins in W at q = 0 (on their axes);
    `homes`: {name: (R (3, 3), p (3,) mm)} at q = 0; `fixed`: the names of frames
    welded to the world (their pose never changes)."""

    def __init__(self, plant, frames: dict):
        context = plant.CreateDefaultContext()  # q = 0
        n = plant.num_positions()
        joints = [plant.get_joint(j) for j in plant.GetJointIndices() if plant.get_joint(j).num_positions() > 0]
        if len(joints) != n or not all(isinstance(j, RevoluteJoint) for j in joints):
            raise ValueError(f"Chain needs a revolute joint per position, got {[type(j).__name__ for j in joints]}")
        by_all = set.intersection(*(set(plant.GetBodiesKinematicallyAffectedBy([j.index()])) for j in joints))
        by_any = set(plant.GetBodiesKinematicallyAffectedBy([j.index() for j in joints]))
        self.homes, self.fixed = {}, set()
        for name, frame in frames.items():
            X = frame.CalcPoseInWorld(context)
            self.homes[name] = (np.ascontiguousarray(X.rotation().matrix()), MM_PER_M * X.translation())
            body = frame.body().index()
            if body not in by_any:
                self.fixed.add(name)
            elif body not in by_all:
                raise ValueError(f"Chain: frame {name!r} moves with some joints only; its body must follow all of them")
        if len(self.fixed) == len(frames):
            raise ValueError("Chain needs at least one frame that moves with the joints")
        S, self.p_WJ = np.empty((6, n)), np.empty((n, 3))
        for joint in joints:  # the twist of a unit rotation about the joint's axis: (w, p x w), p on the axis
            X_WJ = joint.frame_on_child().CalcPoseInWorld(context)  # at q = 0 the joint's two frames coincide
            w = X_WJ.rotation().matrix() @ joint.revolute_axis()
            i = joint.position_start()
            self.p_WJ[i] = MM_PER_M * X_WJ.translation()
            S[:3, i], S[3:, i] = w, np.cross(self.p_WJ[i], w)
        self.S = np.ascontiguousarray(S)
        self.n = n
        # the product runs base to tip in the order of q: hold it to the plant at one posture
        q = np.linspace(-0.7, 0.9, n)
        plant.SetPositions(context, q)
        name = next(k for k in frames if k not in self.fixed)
        X = frames[name].CalcPoseInWorld(context)
        R, p = self.pose(name, q)
        if not (np.allclose(R, X.rotation().matrix(), atol=1e-12) and np.allclose(p, MM_PER_M * X.translation(), atol=1e-9)):
            raise ValueError("Chain: the plant's joints are not a serial chain in the order of q")

    def home(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """The frame's pose at q = 0 (R, p mm); ValueError naming the frames for an unknown one."""
        if name not in self.homes:
            raise ValueError(f"unknown frame {name!r}; the frames are {', '.join(sorted(self.homes))}")
        return self.homes[name]

    def pose(self, name: str, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(R_W<name> (3, 3), p_W<name> (3,) mm) at q (n,) rad (finite, checked by the caller)."""
        R_h, p_h = self.home(name)
        if name in self.fixed:
            return R_h.copy(), p_h.copy()
        return frame_pose(self.S, q, R_h, p_h)

    def pose_and_jacobian(self, name: str, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(R, p mm, spatial Jacobian (6, n) of the frame's origin: angular rad/rad, then
        translational mm/rad) in W at q."""
        R_h, p_h = self.home(name)
        if name in self.fixed:
            return R_h.copy(), p_h.copy(), np.zeros((6, self.n))
        return frame_pose_and_jacobian(self.S, q, R_h, p_h)
