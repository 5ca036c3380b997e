"""Robot kinematics figures: RCM IK per target, the per-step queries of the 1 kHz loop,
RCM differential kinematics against Drake's DoDifferentialInverseKinematics on the same
plant (time, tip tracking, RCM), and Drake's AddPointToLineDistanceConstraint as RCM."""
from __future__ import annotations

import numpy as np
from pydrake.multibody.inverse_kinematics import InverseKinematics
from pydrake.solvers import SnoptSolver

from bench.timing import summary_us, time_calls_us
from planning.diffik import DrakeDiffIK, rcm_joint_velocity
from planning.ik import rcm_ik
from planning.robot import MM_PER_M, Robot
from planning.scan import start_posture
from planning.scenario import SurgeryScenario

RATE_HZ = 1000.0
TIP_SPEED_MM_S = 5.0


def run() -> None:
    scenario = SurgeryScenario()
    robot = Robot(scenario)
    p_WC = scenario.p_WC
    P = scenario.tip_targets_W(scenario.spiral_E())
    q0 = start_posture(robot, P[0], p_WC)

    # IK per target along the spiral (seeded from the previous) and for band targets from the start
    step = P[::10][:300]
    Q = [q0]
    ik_us = time_calls_us(lambda i: Q.append(rcm_ik(robot, step[i], p_WC, Q[-1])), len(step))
    print(f"rcm_ik, spiral every 1 mm, seeded from the previous:  {summary_us(ik_us)}")
    band = scenario.tip_targets_W(scenario.peripheral_band_E())
    ok = []

    def band_ik(i):
        try:
            rcm_ik(robot, band[i], p_WC, q0)
            ok.append(True)
        except ValueError:
            ok.append(False)

    band_us = time_calls_us(band_ik, len(band))
    print(f"rcm_ik, peripheral band from the start posture:      {summary_us(band_us)}   reached {sum(ok)}/{len(band)}")

    # per-step queries of the loop, at distinct postures (no cached kinematics)
    qs = q0 + 1e-4 * np.arange(2000)[:, None] * np.ones(6)
    v = np.array([3.0, -2.0, 1.0])
    print(f"Robot.jacobian('T') per call:                       {summary_us(time_calls_us(lambda i: robot.jacobian('T', np.zeros(3), qs[i]), 2000))}")
    print(f"Robot.rcm_rows per call:                            {summary_us(time_calls_us(lambda i: robot.rcm_rows(qs[i], p_WC), 2000))}")
    print(f"rcm_joint_velocity (ours, KKT) per step:            {summary_us(time_calls_us(lambda i: rcm_joint_velocity(robot, qs[i], v, p_WC), 2000))}")

    drake_step = DrakeDiffIK(robot, RATE_HZ)

    print(f"Drake DoDifferentialInverseKinematics per step:     {summary_us(time_calls_us(lambda i: drake_step(qs[i], v), 2000))}")

    # 2 s of the spiral at 1 kHz, both executors from the same posture
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    t = np.arange(int(2.0 * RATE_HZ)) / RATE_HZ
    ref = np.column_stack([np.interp(t * TIP_SPEED_MM_S, s, P[:, k]) for k in range(3)])
    for name, solve in (("ours (RCM rows)", lambda q, vc: rcm_joint_velocity(robot, q, vc, p_WC)),
                        ("Drake DoDiffIK (no RCM)", drake_step)):
        q, tip_err, rcm_err = q0.copy(), [], []
        for k in range(len(t) - 1):
            p_T = robot.point("T", np.zeros(3), q)
            vc = (ref[k + 1] - ref[k]) * RATE_HZ + 20.0 * (ref[k] - p_T)
            q = q + solve(q, vc) / RATE_HZ
            tip_err.append(np.linalg.norm(robot.point("T", np.zeros(3), q) - ref[k + 1]))
            rcm_err.append(robot.rcm_error_mm(q, p_WC))
        print(f"2 s of spiral at 1 kHz, {name:24s} tip error max {1e3 * max(tip_err):8.2f} um, "
              f"RCM error max {1e3 * max(rcm_err):10.2f} um")

    # Drake's own point-to-line RCM constraint: success and real RCM error on band targets
    errs, fails = [], 0
    for p_T in band:
        ikp = InverseKinematics(robot.plant, with_joint_limits=True)
        ikp.AddPositionConstraint(robot.plant.GetFrameByName("tip"), np.zeros(3), robot.plant.world_frame(), (p_T - 0.01) / MM_PER_M, (p_T + 0.01) / MM_PER_M)
        ikp.AddPointToLineDistanceConstraint(robot.plant.world_frame(), p_WC / MM_PER_M, robot.plant.GetFrameByName("instrument"),
                                             np.zeros(3), np.array([1.0, 0.0, 0.0]), 0.0, 1e-6)
        prog = ikp.get_mutable_prog()
        prog.AddQuadraticErrorCost(np.eye(6), q0, ikp.q())
        prog.SetInitialGuess(ikp.q(), q0)
        result = SnoptSolver().Solve(prog)
        if result.is_success():
            errs.append(robot.rcm_error_mm(result.GetSolution(ikp.q()), p_WC))
        else:
            fails += 1
    worst = f"{1e3 * max(errs):.1f} um" if errs else "n/a"
    print(f"AddPointToLineDistanceConstraint (1 um) alone, band: success {len(errs)}/{len(band)}, "
          f"worst RCM error among 'successes' {worst}")
