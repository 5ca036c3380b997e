"""Inverse kinematics through the trocar (Drake InverseKinematics, RCM as a point-to-line
distance constraint), millimetres and radians at the interface."""
from __future__ import annotations

import numpy as np
from pydrake.multibody.inverse_kinematics import InverseKinematics
from pydrake.solvers import Solve

from planning.robot import MM_PER_M, Robot


_SEED_OFFSETS = [np.zeros(6)] + [np.array(v) for v in (
    [0, 0.2, -0.2, 0, 0.3, 0], [0.2, 0, 0, 0.3, 0, -0.3], [-0.2, 0, 0, -0.3, 0, 0.3], [0, -0.2, 0.3, 0, -0.3, 0])]
_SOLVER_TOL_MM = 0.01  # tolerance given to SNOPT; the Gauss-Newton polish then reaches ~1e-9 mm


class IKFailure(ValueError):
    """The target cannot be reached through the trocar within the joint limits."""


def rcm_ik(robot: Robot, p_WT_mm, p_WC_mm, q_seed, rcm_tol_mm: float = 1e-4, tip_tol_mm: float = 1e-4,
           roll_rad: float | None = None) -> np.ndarray:
    """Joint angles (6,) rad putting the tip T at p_WT_mm with the shaft through the trocar
    p_WC_mm (distance <= rcm_tol_mm), within the joint limits, starting from q_seed (for
    continuity). `roll_rad`, if given, fixes the instrument roll: the angle about the shaft
    of its y axis from the horizontal. Raises IKFailure naming the target otherwise."""
    p_T = np.asarray(p_WT_mm, dtype=float)
    p_C = np.asarray(p_WC_mm, dtype=float)
    q_seed = np.asarray(q_seed, dtype=float)
    for name, v in (("p_WT_mm", p_T), ("p_WC_mm", p_C)):
        if v.shape != (3,) or not np.all(np.isfinite(v)):
            raise ValueError(f"{name} must be a finite (3,) point in mm, got {v}")
    if q_seed.shape != (6,) or not np.all(np.isfinite(q_seed)):
        raise ValueError(f"q_seed must be a finite (6,) joint vector in rad, got {q_seed}")
    plant = robot.plant
    ik = InverseKinematics(plant, with_joint_limits=True)
    tip = plant.GetFrameByName("tip")
    world = plant.world_frame()
    tol_T = _SOLVER_TOL_MM / MM_PER_M  # loose for the solver; polish() makes it exact
    ik.AddPositionConstraint(tip, np.zeros(3), world, p_T / MM_PER_M - tol_T, p_T / MM_PER_M + tol_T)
    ik.AddPointToLineDistanceConstraint(
        world, p_C / MM_PER_M, plant.GetFrameByName("instrument"), np.zeros(3), np.array([1.0, 0.0, 0.0]),
        0.0, _SOLVER_TOL_MM / MM_PER_M,
    )
    if roll_rad is not None:
        # the instrument's y axis makes angle roll with the horizontal plane: y . z_W = sin(roll)
        ik.AddAngleBetweenVectorsConstraint(plant.GetFrameByName("instrument"), np.array([0.0, 1.0, 0.0]), world,
                                            np.array([0.0, 0.0, 1.0]), np.pi / 2 - roll_rad - 1e-6, np.pi / 2 - roll_rad + 1e-6)
    q = ik.q()
    prog = ik.get_mutable_prog()
    prog.AddQuadraticErrorCost(np.eye(6), q_seed, q)  # stay near the seed: continuity
    result = None
    # The seed first (continuity); SNOPT is local, so a few nearby wrist/base variants after.
    for dq in _SEED_OFFSETS:
        prog.SetInitialGuess(q, np.clip(q_seed + dq, robot.q_lower, robot.q_upper))
        result = Solve(prog)
        if result.is_success():
            break
    if not result.is_success():
        raise IKFailure(f"tip target {np.round(p_T, 3)} mm is not reachable through the trocar "
                        f"{np.round(p_C, 3)} mm within the joint limits ({result.get_solver_id().name()})")
    q_sol = polish(robot, result.GetSolution(q), p_T, p_C)
    tip_err = np.linalg.norm(robot.point("T", np.zeros(3), q_sol) - p_T)
    if np.any(robot.joint_margin_rad(q_sol) < 0) or robot.rcm_error_mm(q_sol, p_C) > rcm_tol_mm or tip_err > tip_tol_mm:
        raise IKFailure(f"tip target {np.round(p_T, 3)} mm: no solution within the joint limits and RCM tolerance")
    return q_sol


def polish(robot: Robot, q, p_WT_mm, p_WC_mm, iterations: int = 4) -> np.ndarray:
    """Gauss-Newton (minimum-norm) steps on the tip position and the two lateral RCM
    errors, in mm: Drake's point-to-line constraint bounds the squared distance in m^2,
    which leaves micrometre errors at the solver's tolerance; a few exact steps remove them."""
    q = np.asarray(q, dtype=float).copy()
    for _ in range(iterations):
        A, b = robot.rcm_rows(q, p_WC_mm, gain_per_s=1.0)  # b = -(lateral RCM error), mm
        r = np.concatenate([robot.point("T", np.zeros(3), q) - p_WT_mm, -b])
        J = np.vstack([robot.jacobian("T", np.zeros(3), q), A])
        q -= np.linalg.lstsq(J, r, rcond=None)[0]
    return q
