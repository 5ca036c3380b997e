"""The instrument's way out of the eye, between the trocars and back in (planning.multiport).

A pass enters and leaves along the shaft line of its first and last cell (line_trajectory:
the tip from EXIT_MM outside the trocar, or as far as the arm reaches with every joint
JOINT_MARGIN_RAD inside its range but at least MIN_EXIT_MM, at INSERT_SPEED_MM_S).
Between passes the instrument moves outside the eye (joint_move: the tip on an arc about
the eye centre at MOVE_SPEED_MM_S, through a via posture where a joint would leave its
range on the arc); every piece timed within the
joints' speed limits (planning.scan.joint_trajectory) and JOINT_MARGIN_RAD inside their
ranges: the margin the safety filter keeps in the loop (safety.inputs.FilterConfig), here
where no filter runs. Units: mm, s, rad; frame W.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydrake.trajectories import PiecewisePolynomial

from planning.closed_form import shaft_ik
from planning.ik import IKFailure, rcm_ik
from planning.robot import Robot
from planning.scan import joint_trajectory
from planning.scenario import EYE_WALL_MM
from safety.inputs import FilterConfig

EXIT_MM = 10.0  # the tip's distance outside the trocar while the instrument moves between ports
MIN_EXIT_MM = 2.0  # the least the tip must clear the trocar by before the instrument moves
INSERT_SPEED_MM_S = 5.0  # tip speed along the shaft while inserting and withdrawing
LINE_STEP_MM = 1.0  # spacing of the insertion line's IK waypoints
MOVE_SPEED_MM_S = 20.0  # the tip's speed on the move outside the eye
MOVE_CLEARANCE_MM = 5.0  # the tip's arc between ports lies this much further out than its ends
MOVE_MIN_OUTSIDE_MM = EYE_WALL_MM  # the move's tip stays outside the eye wall (retina, choroid, sclera)
LIMIT_CHECK_DT_S = 0.005  # a move's joint ranges checked this often along its spline
JOINT_MARGIN_RAD = FilterConfig().joint_margin_rad  # every joint this far inside its range outside the eye


@dataclass(frozen=True)
class PortSwitch:
    """A planned switch between ports: durations (s) of its withdraw, move and insert, and the
    tip's smallest distance outside the model's retina during the move (mm, > 0 outside)."""

    from_port: str
    to_port: str
    withdraw_s: float
    move_s: float
    insert_s: float
    move_min_outside_mm: float

    @property
    def duration_s(self) -> float:
        return self.withdraw_s + self.move_s + self.insert_s


def line_trajectory(robot: Robot, q_end, p_WT, p_WC, roll_rad: float, length_mm: float, speed_mm_s: float,
                    min_length_mm: float):
    """(joint trajectory rad, its length mm) of the tip moving along the shaft line trocar
    p_WC -> p_WT to p_WT from up to `length_mm` behind it (outside the eye when longer
    than |p_WT - p_WC|), ending at q_end; timed at `speed_mm_s` (planning.scan.joint_trajectory)
    with the roll held. The line starts where the arm still reaches it with every joint
    JOINT_MARGIN_RAD inside its range (IK every LINE_STEP_MM, the curve between checked
    every LIMIT_CHECK_DT_S); IKFailure when that is less than `min_length_mm`."""
    p_T, p_C = np.asarray(p_WT, dtype=float), np.asarray(p_WC, dtype=float)
    u = (p_T - p_C) / np.linalg.norm(p_T - p_C)
    pivot = p_T - (length_mm + 20.0) * u  # the same line, its pivot behind every point of the move
    s = np.linspace(0.0, length_mm, max(int(np.ceil(length_mm / LINE_STEP_MM)), 1) + 1)
    Q = [np.asarray(q_end, dtype=float)]
    for d in s[1:]:
        try:
            q = rcm_ik(robot, p_T - d * u, pivot, Q[-1], roll_rad=roll_rad)
        except IKFailure:
            break
        if np.min(robot.joint_margin_rad(q)) < JOINT_MARGIN_RAD:
            break
        Q.append(q)
    while True:  # the curve between waypoints kept within the margin too, shortened where not
        reached = s[len(Q) - 1]
        if reached < min_length_mm:
            raise IKFailure(f"the instrument cannot leave the trocar along its shaft from p_WT_mm = {np.round(p_T, 3)}: "
                            f"the arm reaches {reached:.1f} mm of the {min_length_mm:.1f} mm needed "
                            f"with every joint {np.degrees(JOINT_MARGIN_RAD):.1f} deg inside its range")
        traj = joint_trajectory(robot, np.array(Q[::-1]), p_T - s[:len(Q)][::-1, None] * u, speed_mm_s)
        if not _leaves_limits(robot, traj):
            return traj, float(reached)
        Q = Q[:-1]


def joint_move(robot: Robot, q0, q1, p_WE, clearance_mm: float, model=None) -> PiecewisePolynomial:
    """The move outside the eye between two postures q0, q1 (rad) whose tips are outside
    it: the tip on an arc about the eye centre p_WE (mm, W) bulging `clearance_mm` further
    out than the line between the tips' own distances, the shaft direction turning evenly
    between its two (closed-form IK, the branch nearest the last sample), timed at
    MOVE_SPEED_MM_S within the joints' speed limits (planning.scan.joint_trajectory).
    Where a joint would leave its range on the arc (both ends near a wrist limit), through
    a via posture: the tip `clearance_mm` beyond the further end on the mean of the ends'
    directions from the eye centre, the shaft pointing at the centre, each leg an arc (or
    a direct joint-space move where the arm cannot follow it); a direct joint-space move
    last (at rest at both ends, it stays between them). Every posture keeps JOINT_MARGIN_RAD
    inside the joints' ranges; a candidate whose curve comes nearer between its waypoints
    is skipped. With `model` (the retina, W), the first of these whose tip keeps
    MOVE_MIN_OUTSIDE_MM outside it, else the one keeping furthest out."""
    q0, q1 = np.asarray(q0, dtype=float), np.asarray(q1, dtype=float)
    candidates = []
    arc = _arc(robot, q0, q1, p_WE, clearance_mm)
    if arc is not None:
        candidates.append(arc)
    via = _via_posture(robot, q0, q1, p_WE, clearance_mm)
    if via is not None:
        legs = [_arc(robot, a, b, p_WE, clearance_mm) for a, b in ((q0, via), (via, q1))]
        legs = [np.array([a, b]) if leg is None else leg for leg, (a, b) in zip(legs, ((q0, via), (via, q1)))]
        candidates.append(np.vstack([legs[0], legs[1][1:]]))
    candidates.append(np.array([q0, q1]))
    best, best_out = None, -np.inf
    for k, Q in enumerate(candidates):
        traj = joint_trajectory(robot, Q, np.array([robot.pose("T", q)[1] for q in Q]), MOVE_SPEED_MM_S)
        if k < len(candidates) - 1 and _leaves_limits(robot, traj):
            continue
        if model is None:
            return traj
        out = move_min_outside_mm(robot, traj, model)
        if out >= MOVE_MIN_OUTSIDE_MM:
            return traj
        if out > best_out:
            best, best_out = traj, out
    return best


def _leaves_limits(robot: Robot, move: PiecewisePolynomial) -> bool:
    """Whether a joint comes within JOINT_MARGIN_RAD of its range's ends on the trajectory
    `move`, sampled every LIMIT_CHECK_DT_S (planning.scan.joint_trajectory keeps a joint
    within its waypoints' range where they run monotone, not elsewhere)."""
    ts = np.append(np.arange(move.start_time(), move.end_time(), LIMIT_CHECK_DT_S), move.end_time())
    return bool(np.min(robot.joint_margin_rad(move.vector_values(ts).T)) < JOINT_MARGIN_RAD - 1e-12)


def move_min_outside_mm(robot: Robot, move: PiecewisePolynomial, model, samples: int = 50) -> float:
    """The tip's smallest distance (mm) outside `model` (> 0 outside) along the joint trajectory `move`."""
    ts = np.linspace(move.start_time(), move.end_time(), samples)
    tips = np.array([robot.pose("T", q)[1] for q in move.vector_values(ts).T])
    return float(-np.max(np.asarray(model.signed_distance(tips), dtype=float)))


def _arc(robot: Robot, q0, q1, p_WE, clearance_mm: float) -> np.ndarray | None:
    """joint_move's arc as joint waypoints (13, 6) rad, ends included; None where a sample
    has no closed-form posture JOINT_MARGIN_RAD inside the joint limits."""
    R0, t0 = robot.pose("I", q0)[0], robot.pose("T", q0)[1]
    R1, t1 = robot.pose("I", q1)[0], robot.pose("T", q1)[1]
    d0, d1 = t0 - p_WE, t1 - p_WE
    r0, r1 = np.linalg.norm(d0), np.linalg.norm(d1)
    Q = [q0]
    for s in np.linspace(0.0, 1.0, 13)[1:-1]:
        d = (1 - s) * d0 / r0 + s * d1 / r1
        u = (1 - s) * R0[:, 0] + s * R1[:, 0]
        r = (1 - s) * r0 + s * r1 + clearance_mm * np.sin(np.pi * s)
        cands = shaft_ik(robot.arm, p_WE + r * d / np.linalg.norm(d), u / np.linalg.norm(u), q0[5] + s * (q1[5] - q0[5]))
        ok = [c for c in cands if np.all(robot.joint_margin_rad(c) >= JOINT_MARGIN_RAD)]
        if not ok:
            return None
        Q.append(min(ok, key=lambda c: np.abs(c - Q[-1]).max()))
    return np.array(Q + [q1])


def _via_posture(robot: Robot, q0, q1, p_WE, clearance_mm: float) -> np.ndarray | None:
    """joint_move's via posture (6,) rad (the closed-form branch with the largest joint
    margin), or None when the arm has none JOINT_MARGIN_RAD inside its limits."""
    t0, t1 = robot.pose("T", q0)[1] - p_WE, robot.pose("T", q1)[1] - p_WE
    d = t0 / np.linalg.norm(t0) + t1 / np.linalg.norm(t1)
    d /= np.linalg.norm(d)
    r = max(np.linalg.norm(t0), np.linalg.norm(t1)) + clearance_mm
    cands = [c for c in shaft_ik(robot.arm, p_WE + r * d, -d, 0.5 * (q0[5] + q1[5]))
             if np.all(robot.joint_margin_rad(c) >= JOINT_MARGIN_RAD)]
    return max(cands, key=lambda c: np.min(robot.joint_margin_rad(c))) if cands else None


def port_switches(robot: Robot, model, segments: list, p_WE) -> tuple[list, list]:
    """(PortSwitch, its move outside the eye (joint_move)) between consecutive segments
    (planning.multiport.PortSegment, in execution order) about the eye centre p_WE (mm, W)."""
    switches, moves = [], []
    for a, b in zip(segments[:-1], segments[1:]):
        q0, q1 = a.withdraw.value(a.withdraw.end_time())[:, 0], b.insert.value(0.0)[:, 0]
        move = joint_move(robot, q0, q1, p_WE, MOVE_CLEARANCE_MM, model)
        switches.append(PortSwitch(a.port.name, b.port.name, a.withdraw.end_time(), move.end_time(), b.insert.end_time(),
                                   move_min_outside_mm(robot, move, model)))
        moves.append(move)
    return switches, moves
