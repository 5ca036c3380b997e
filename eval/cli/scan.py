"""`vitreoguard scan`: the paper's spiral executed by the Meca500 through the trocar in the
`surgery` scenario; writes scan.json and scan.png (RCM error and joint margins over time).

Top-level figures are the IK executor's (waypoint IK + shape-preserving joint cubic, sampled at
1 kHz); "diffik" holds the same figures for RCM differential kinematics at 1 kHz.
"""
from __future__ import annotations

import numpy as np

from eval.cli.args import number, out_dir
from eval.cli.io import prepare_out_dir, save_figure, write_json
from eval.cli.progress import phase

TIP_SPEED = number(0.1, 50.0, "mm/s")
REVOLUTIONS = number(0.5, 18.0, "revolutions")
FIGURE_KEYS = ("max_rcm_error_um", "mean_rcm_error_um", "min_joint_margin_deg", "max_joint_speed_fraction", "duration_s")


def register(sub) -> None:
    p = sub.add_parser("scan", help="spiral scan through the trocar (surgery scenario): scan.json, scan.png")
    p.add_argument("--out", type=out_dir, required=True, help="output directory")
    p.add_argument("--tip-speed-mm-s", type=TIP_SPEED, default=5.0, help=f"tip speed along the spiral, {TIP_SPEED.range}")
    p.add_argument("--revolutions", type=REVOLUTIONS, default=18.0,
                   help=f"spiral revolutions over its 9 mm radius, {REVOLUTIONS.range} (paper: 18)")
    p.add_argument("--meshcat", action="store_true", help="show robot, eye, trocar and tip path in Meshcat and wait")
    p.set_defaults(func=run)


def run(args) -> int:
    out = prepare_out_dir(args.out)
    from planning.robot import Robot
    from planning.scan import plan_ik_scan, run_diffik, sample_ik_run
    from planning.scenario import SurgeryScenario

    scenario = SurgeryScenario()
    robot = Robot(scenario)
    P_WT = scenario.tip_targets_W(scenario.spiral_E(revolutions=args.revolutions))
    with phase(f"planning the spiral's joint trajectory ({len(P_WT)} tip targets, IK)"):
        traj, P_used, ik_ms = plan_ik_scan(robot, P_WT, scenario.p_WC, args.tip_speed_mm_s)
        ik = sample_ik_run(robot, traj, P_WT, scenario.p_WC, args.tip_speed_mm_s, solve_ms=ik_ms)
    with phase("the spiral by differential kinematics at 1 kHz"):
        dk = run_diffik(robot, P_WT, scenario.p_WC, ik.q[0], args.tip_speed_mm_s)
    result = {**ik.figures(robot), "executor": "ik", "tip_speed_mm_s": args.tip_speed_mm_s,
              "spiral_points": len(P_WT), "ik_waypoints": len(P_used), "diffik": dk.figures(robot)}
    save_figure(_figure(robot, ik, dk), out / "scan.png")
    write_json(out / "scan.json", result)
    for key in FIGURE_KEYS:
        print(f"{key:28s} ik {result[key]:12.4f}   diffik {result['diffik'][key]:12.4f}")
    if args.meshcat:
        from planning.view import show_scan

        url = show_scan(robot, ik, P_WT)
        input(f"Meshcat at {url}: press Enter to quit ")
    return 0


def _figure(robot, ik, dk):
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    a.semilogy(dk.t, np.maximum(dk.rcm_error_um, 1e-6), lw=0.6, label="differential kinematics, 1 kHz")
    a.semilogy(ik.t, np.maximum(ik.rcm_error_um, 1e-6), lw=0.6, label="IK waypoints + spline")
    a.set_ylabel("RCM error (um)")
    a.legend(loc="lower right")
    margin = np.degrees(np.minimum(ik.q - robot.q_lower, robot.q_upper - ik.q))
    for j in range(6):
        b.plot(ik.t, margin[:, j], lw=0.8, label=f"J{j + 1}")
    b.axhline(5.0, color="k", ls="--", lw=0.6)
    b.set_ylabel("joint margin to limit (deg)")
    b.set_xlabel("time (s)")
    b.legend(ncol=6, fontsize=7, loc="upper right")
    return fig
