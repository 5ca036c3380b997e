"""Inverse kinematics through the trocar: Drake `InverseKinematics` at the mm/rad interface.

The RCM is the point-to-line condition "the trocar C lies on the shaft axis": Drake's
`AddPointToLineDistanceConstraint` (trocar point, shaft line of frame I). It states the
condition through the squared distance, whose gradient vanishes exactly at the solution
(distance 0), so from a distant seed SNOPT stalls or reports success hundreds of
micrometres off the line (bench_robot measures it). Hence the first initial guess is the
exact closed-form solution (planning.closed_form) of the seed's branch, where SNOPT only
has to confirm it (with the roll and seed-distance cost); a few exact Gauss-Newton steps
then take the tip and RCM errors to numerical zero, and the result is checked against
the joint limits. With the roll given the solutions are isolated and the closed-form one
is already exact: it is returned without SNOPT when it checks out (the planner's case);
SNOPT takes over from it and the other seeds otherwise.
"""
from __future__ import annotations

import numpy as np
from pydrake.multibody.inverse_kinematics import InverseKinematics
from pydrake.solvers import SnoptSolver

from planning.closed_form import shaft_ik
from planning.robot import MM_PER_M, Robot

_SOLVER_TOL_MM = 1e-2  # box tolerance given to SNOPT; the polish then reaches ~1e-9 mm
# Seeds tried after the caller's (SNOPT is local): small base/elbow changes and the
# spherical wrist's flipped twin (J4 + pi, -J5, J6 + pi), which reaches the same flange pose.
_SEED_OFFSETS = [np.array(v, dtype=float) for v in (
    [0, 0.2, -0.2, 0, 0.3, 0], [0.2, 0, 0, 0.3, 0, -0.3], [-0.2, 0, 0, -0.3, 0, 0.3], [0, -0.2, 0.3, 0, -0.3, 0])]


class IKFailure(ValueError):
    """The tip target cannot be reached through the trocar within the joint limits."""


def _finite(v, name: str, shape: tuple[int, ...], unit: str) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be a finite {shape} array in {unit}, got {np.asarray(v)!r}")
    return a


VERTICAL_SHAFT_DEG = 1.0  # within this of z_W the roll from the horizontal is undefined


def has_roll(p_WT_mm, p_WC_mm) -> bool:
    """Whether the shaft from the trocar C to the tip T (mm, W) has a roll from the
    horizontal: it lies more than VERTICAL_SHAFT_DEG from vertical."""
    u = np.asarray(p_WT_mm, dtype=float) - np.asarray(p_WC_mm, dtype=float)
    return bool(np.linalg.norm(np.cross([0.0, 0.0, 1.0], u / np.linalg.norm(u))) >= np.sin(np.radians(VERTICAL_SHAFT_DEG)))


def roll_direction_W(p_WT_mm, p_WC_mm, roll_rad: float) -> np.ndarray:
    """Unit direction (3,) in W of the instrument's y axis for a shaft from the trocar C
    to the tip T rolled by `roll_rad` about the shaft: roll 0 is horizontal (along
    z_W x u), positive roll turns it about u (right-handed). Raises ValueError when the
    shaft is within 1 deg of vertical (roll from the horizontal is undefined there)."""
    if not has_roll(p_WT_mm, p_WC_mm):
        raise ValueError("roll_rad is undefined for a vertical shaft (within 1 deg of z_W); give roll_rad=None")
    u = np.asarray(p_WT_mm, dtype=float) - np.asarray(p_WC_mm, dtype=float)
    u /= np.linalg.norm(u)
    h = np.cross([0.0, 0.0, 1.0], u)
    h /= np.linalg.norm(h)
    return np.cos(roll_rad) * h + np.sin(roll_rad) * np.cross(u, h)


def rcm_ik(robot: Robot, p_WT_mm, p_WC_mm, q_seed, *, roll_rad: float | None = None,
           rcm_tol_mm: float = 1e-4, tip_tol_mm: float = 1e-4) -> np.ndarray:
    """Joint angles (6,) rad putting the tip T at p_WT_mm (3,) mm with the shaft through
    the trocar p_WC_mm (3,) mm, within the joint limits, as close as possible to q_seed
    (6,) rad (continuity along a path). `roll_rad` (optional) fixes the instrument's roll
    about the shaft (see `roll_direction_W`); otherwise the closest roll to the seed wins.

    Raises ValueError for non-finite input, IKFailure (a ValueError) naming the target
    when no solution within the limits and tolerances (mm) exists from the seeds tried.
    """
    p_T = _finite(p_WT_mm, "p_WT_mm", (3,), "mm")
    p_C = _finite(p_WC_mm, "p_WC_mm", (3,), "mm")
    q_seed = _finite(q_seed, "q_seed", (6,), "rad")
    if np.linalg.norm(p_T - p_C) < 1.0:
        raise ValueError(f"p_WT_mm must be at least 1 mm from the trocar p_WC_mm, got {np.linalg.norm(p_T - p_C):.3g} mm")
    y_W = None if roll_rad is None else roll_direction_W(p_T, p_C, float(_finite(roll_rad, "roll_rad", (), "rad")))
    exact = _closed_form_guess(robot, p_T, p_C, q_seed, y_W)

    def checked(q_try):  # (polished solution or None, why not)
        q_sol = polish(robot, q_try, p_T, p_C)
        if y_W is not None:  # J6 turns about the shaft: restore the roll the polish disturbed
            q_sol[5] += signed_angle(robot.pose("I", q_sol)[0][:, 1], y_W, (p_T - p_C) / np.linalg.norm(p_T - p_C))
        tip_err = float(np.linalg.norm(robot.point("T", np.zeros(3), q_sol) - p_T))
        rcm_err = robot.rcm_error_mm(q_sol, p_C)
        if np.all(robot.joint_margin_rad(q_sol) >= 0) and rcm_err <= rcm_tol_mm and tip_err <= tip_tol_mm:
            return q_sol, None
        return None, f"polished solution off by tip {tip_err:.2g} mm, RCM {rcm_err:.2g} mm or beyond a joint limit"

    if y_W is not None and exact is not None:
        # with the roll fixed, tip + RCM + roll are six conditions on six joints: the
        # solutions are isolated, and the closed-form one of the seed's branch is exact,
        # so SNOPT would only confirm it (at ~6 ms a solve): it is taken when it checks out
        q_sol, _ = checked(exact)
        if q_sol is not None:
            return q_sol
    prog, q = _program(robot, p_T, p_C, q_seed, y_W)
    solver = SnoptSolver()
    last = None
    seeds = [q_seed] + [q_seed + dq for dq in _SEED_OFFSETS] + [_wrist_flip(q_seed)]
    for guess in ([] if exact is None else [exact]) + seeds:
        prog.SetInitialGuess(q, np.clip(guess, robot.q_lower, robot.q_upper))
        result = solver.Solve(prog)
        if result.is_success():
            q_sol, last = checked(result.GetSolution(q))
            if q_sol is not None:
                return q_sol
        else:
            last = f"{result.get_solver_id().name()}: {result.get_solution_result().name}"
    raise IKFailure(f"tip target p_WT_mm = {np.round(p_T, 3)} is not reachable through the trocar "
                    f"p_WC_mm = {np.round(p_C, 3)} within the joint limits ({last})")


def _closed_form_guess(robot: Robot, p_T: np.ndarray, p_C: np.ndarray, q_seed: np.ndarray, y_W=None):
    """The exact closed-form solution (6,) rad of the seed's branch (nearest to the seed; J6
    kept, or turned to the roll y_W when given), or None when the closed form has none."""
    u = (p_T - p_C) / np.linalg.norm(p_T - p_C)
    exact = shaft_ik(robot.arm, p_T, u, q_seed[5])
    if not len(exact):
        return None
    q = exact[np.argmin(np.abs((exact - q_seed + np.pi) % (2 * np.pi) - np.pi).sum(axis=1))].copy()
    if y_W is not None:  # J6 turns about the shaft: the exact roll in closed form
        q[5] += signed_angle(robot.pose("I", q)[0][:, 1], y_W, u)
        q[5] = q_seed[5] + (q[5] - q_seed[5] + np.pi) % (2 * np.pi) - np.pi  # the turn nearest the seed
    return q


def signed_angle(a: np.ndarray, b: np.ndarray, axis: np.ndarray) -> float:
    """Angle (rad) turning a onto b about the unit axis (both perpendicular to it)."""
    return float(np.arctan2(np.cross(a, b) @ axis, a @ b))


def _wrist_flip(q: np.ndarray) -> np.ndarray:
    """The other spherical-wrist solution with the same flange pose, wrapped into (-pi, pi]."""
    f = q + np.array([0.0, 0.0, 0.0, np.pi, 0.0, np.pi])
    f[4] = -q[4]
    return (f + np.pi) % (2 * np.pi) - np.pi


def _program(robot: Robot, p_T: np.ndarray, p_C: np.ndarray, q_seed: np.ndarray, y_W):
    """The IK program (metres inside): tip box, RCM in the shaft frame, optional roll,
    joint limits, and the quadratic distance to the seed as cost."""
    plant = robot.plant
    world = plant.world_frame()
    shaft = plant.GetFrameByName("instrument")
    tol = _SOLVER_TOL_MM / MM_PER_M
    ik = InverseKinematics(plant, with_joint_limits=True)
    ik.AddPositionConstraint(plant.GetFrameByName("tip"), np.zeros(3), world, p_T / MM_PER_M - tol, p_T / MM_PER_M + tol)
    ik.AddPointToLineDistanceConstraint(world, p_C / MM_PER_M, shaft, np.zeros(3), np.array([1.0, 0.0, 0.0]), 0.0, tol)
    if y_W is not None:
        ik.AddAngleBetweenVectorsConstraint(shaft, np.array([0.0, 1.0, 0.0]), world, y_W, 0.0, 1e-4)
    q = ik.q()
    prog = ik.get_mutable_prog()
    prog.AddQuadraticErrorCost(np.eye(6), q_seed, q)
    return prog, q


def polish(robot: Robot, q, p_WT_mm, p_WC_mm, iterations: int = 3) -> np.ndarray:
    """q (6,) rad after minimum-norm Gauss-Newton steps on the tip position error and the
    two lateral RCM errors (mm): removes the solver's tolerance-level residuals."""
    q = np.asarray(q, dtype=float).copy()
    for _ in range(iterations):
        A, b = robot.rcm_rows(q, p_WC_mm, gain_per_s=1.0)  # b = -(lateral RCM error), mm
        r = np.concatenate([robot.point("T", np.zeros(3), q) - p_WT_mm, -b])
        J = np.vstack([robot.jacobian("T", np.zeros(3), q), A])
        q -= np.linalg.lstsq(J, r, rcond=None)[0]
    return q
