"""`vitreoguard calibrate`: the paper's plate calibration of the sensor pose, and its Fig. 3.

Simulates the plate calibration (flange poses from `models.calibration.plate.sample_flange_poses`
until the Meca500 plant provides reachable ones; true sensor pose offset from the
nominal one; N(0, noise) distances), recovers the sensor pose with SLSQP and writes
`calibration.json` (recovered vs true) and `fig3_sensitivity.png` (sphere-diameter
error when the sensor pose is perturbed vertically and rotated).
"""
from __future__ import annotations

import math
import time

import matplotlib.pyplot as plt
import numpy as np

from eval.cli.args import SEED, integer, number, out_dir
from eval.cli.io import prepare_out_dir, save_figure, write_json
from eval.cli.progress import phase
from models.calibration.plate import (
    Plane,
    SensorPose,
    calibrate_sensor,
    direction_error_deg,
    offset_sensor_pose,
    plate_distances,
    position_error_um,
    sample_flange_poses,
)
from models.calibration.sensitivity import SPHERE_RADIUS_MM, diameter_error_um, diameter_sensitivity, sphere_eye
from models.calibration.uncertainty import calibration_uncertainty
from models.scan.paper_scan import paper_scan



def nominal_sensor() -> SensorPose:
    """The nominal iiOCT sensor pose in the flange frame, from the robot model
    (planning/data/meca500.urdf: the fibre at the tip, the beam along the shaft)."""
    from planning.robot import Robot

    robot = Robot()
    q0 = np.zeros(robot.nq)
    R_WF, p_WF = robot.pose("F", q0)
    R_WS, p_WS = robot.pose("S", q0)
    return SensorPose(R_WF.T @ (p_WS - p_WF), R_WF.T @ R_WS[:, 2])

# A level plate in front of the robot, 50 mm above its base (W: robot base, mm).
PLATE = Plane([0.0, 0.0, 1.0], -50.0)
PLATE_CENTRE_W = (250.0, 0.0, 50.0)
# Targets of the calibration (the paper's residual: 30.03 um).
TARGETS = {"position_error_um": 20.0, "direction_error_deg": 0.1, "plane_residual_um": 30.03}
# Option limits: beyond them the sampler's 2 mm minimum distance at 65 deg incidence
# could put the true beam origin behind the plate; they cover realistic mounting errors.
POSES = integer(10, 10_000)
NOISE_UM = number(0.0, 500.0, "um")
OFFSET_UM = number(0.0, 500.0, "um")
TILT_DEG = number(0.0, 5.0, "deg")
FIG3_OFFSETS_UM = np.linspace(-200.0, 200.0, 41)
FIG3_TILTS_DEG = np.linspace(0.0, 2.0, 21)
FIG3_AZIMUTHS_DEG = (0.0, 90.0, 180.0, 270.0)


def register(sub) -> None:
    p = sub.add_parser("calibrate", help="plate calibration of the sensor pose: calibration.json, fig3_sensitivity.png")
    p.add_argument("--out", type=out_dir, required=True, help="output directory")
    p.add_argument("--poses", type=POSES, default=250, help=f"number of flange poses, {POSES.range} (paper: 250)")
    p.add_argument("--noise-um", type=NOISE_UM, default=20.0, help=f"SD of the distance noise, {NOISE_UM.range}")
    p.add_argument("--seed", type=SEED, default=0, help=f"random seed, {SEED.range}")
    p.add_argument("--offset-um", type=OFFSET_UM, default=300.0,
                   help=f"true sensor origin's distance from the nominal one, {OFFSET_UM.range}")
    p.add_argument("--tilt-deg", type=TILT_DEG, default=2.0, help=f"true beam's angle from the nominal one, {TILT_DEG.range}")
    p.set_defaults(func=main)


def _pose_dict(sensor: SensorPose, plane: Plane) -> dict:
    return {"p_FS_mm": sensor.p_FS.tolist(), "u_F": sensor.u_F.tolist(),
            "plane_normal_W": plane.normal_W.tolist(), "plane_offset_mm": plane.offset_mm}


def _uncertainty_dict(u) -> dict:
    mm, deg = u.bound(3.0)
    return {"along_beam_mm": u.along_mm, "across_beam_mm": u.across_mm, "direction_deg": u.direction_deg,
            "bound_3_sigma": {"mm": mm, "deg": deg}}


def run_calibration(args) -> dict:
    """The calibration experiment for validated `args`: the calibration.json content."""
    rng = np.random.default_rng(args.seed)
    nominal = nominal_sensor()
    truth = offset_sensor_pose(nominal, args.offset_um * 1e-3, math.radians(args.tilt_deg), rng)
    R_WF, p_WF = sample_flange_poses(args.poses, nominal, PLATE, rng, centre_W=PLATE_CENTRE_W)
    distances = plate_distances(R_WF, p_WF, truth, PLATE, args.noise_um, rng)
    result = calibrate_sensor(R_WF, p_WF, distances)
    out = {
        "position_error_um": position_error_um(result.sensor, truth),
        "direction_error_deg": direction_error_deg(result.sensor, truth),
        "plane_residual_um": result.residual_rms_um,
        "plane_residual_max_um": result.residual_max_um,
        "n_poses": args.poses,
        "noise_um": args.noise_um,
        "seed": args.seed,
        "nominal": {"p_FS_mm": nominal.p_FS.tolist(), "u_F": nominal.u_F.tolist()},
        "true": _pose_dict(truth, PLATE),
        "recovered": _pose_dict(result.sensor, result.plane),
        "solve_time_s": result.solve_time_s,
        "n_starts": result.n_starts,
        "n_starts_at_best": result.n_at_best,
        "converged": result.converged,
        # the part of the position error that moves retinal points along the beam
        "axial_error_um": float(1e3 * (result.sensor.p_FS - truth.p_FS) @ truth.u_F),
        # the fit's own standard errors (models.calibration.uncertainty) and the bound of 3 of
        # them, what `--calibration-bound MM,DEG` declares to the filter
        "uncertainty": _uncertainty_dict(calibration_uncertainty(R_WF, p_WF, distances, result)),
        "targets": TARGETS,
    }
    out["meets_targets"] = {k: out[k] <= v for k, v in TARGETS.items()}
    return out


def run_sensitivity(calibration: dict) -> dict:
    """Fig. 3 data (noise-free scan of a 12 mm sphere), plus the diameter error that this
    calibration's axial and direction errors cause (worst tilt azimuth)."""
    curves = diameter_sensitivity(FIG3_OFFSETS_UM, FIG3_TILTS_DEG, FIG3_AZIMUTHS_DEG)
    scan = paper_scan(sphere_eye(), noise_um=0.0)
    achieved = [diameter_error_um(scan, SPHERE_RADIUS_MM, calibration["axial_error_um"] * 1e-3,
                                  math.radians(calibration["direction_error_deg"]), math.radians(az)) for az in FIG3_AZIMUTHS_DEG]
    return {
        "sphere_radius_mm": SPHERE_RADIUS_MM,
        "offsets_um": curves.offsets_um.tolist(),
        "offset_diameter_error_um": curves.offset_diameter_error_um.tolist(),
        "tilts_deg": curves.tilts_deg.tolist(),
        "azimuths_deg": curves.azimuths_deg.tolist(),
        "tilt_diameter_error_um": curves.tilt_diameter_error_um.tolist(),
        "diameter_error_from_this_calibration_um": max(achieved, key=abs),
    }


def figure_sensitivity(s: dict, calibration: dict):
    """Two panels: diameter error (um) vs vertical offset (um) and vs tilt (deg)."""
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    ax1.plot(s["offsets_um"], s["offset_diameter_error_um"], color="tab:blue", lw=1.8)
    ax1.axvline(calibration["axial_error_um"], color="black", ls="--", lw=1,
                label=f"this calibration: {calibration['axial_error_um']:.1f} um")
    ax1.set_xlabel("vertical offset of the sensor along the beam (um)")
    ax1.set_ylabel("sphere-diameter error (um)")
    ax1.set_title("(a) vertical perturbation")
    for az, errs in zip(s["azimuths_deg"], s["tilt_diameter_error_um"]):
        ax2.plot(s["tilts_deg"], errs, lw=1.5, label=f"tilt axis at {az:g} deg")
    ax2.axvline(calibration["direction_error_deg"], color="black", ls="--", lw=1,
                label=f"this calibration: {calibration['direction_error_deg']:.3f} deg")
    ax2.set_xlabel("tilt of the beam (deg)")
    ax2.set_title("(b) rotation")
    for ax in (ax1, ax2):
        ax.axhline(0.0, color="gray", lw=0.6)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(f"Sphere-diameter error under a sensor-pose error (noise-free spiral scan of a "
                 f"{s['sphere_radius_mm']:g} mm sphere, trocar at z = 8 mm)")
    fig.tight_layout()
    return fig


def main(args) -> int:
    out = prepare_out_dir(args.out)
    t0 = time.perf_counter()
    with phase(f"calibrating the sensor pose from {args.poses} plate distances"):
        calibration = run_calibration(args)
    with phase("sphere-diameter sensitivity (Fig. 3)"):
        calibration["sensitivity"] = run_sensitivity(calibration)
    fig = figure_sensitivity(calibration["sensitivity"], calibration)
    save_figure(fig, out / "fig3_sensitivity.png")
    write_json(out / "calibration.json", calibration)
    c = calibration
    print(f"wrote {out / 'calibration.json'} and {out / 'fig3_sensitivity.png'} in {time.perf_counter() - t0:.1f} s")
    print(f"  position error {c['position_error_um']:.1f} um (target <= {TARGETS['position_error_um']:g}), "
          f"direction error {c['direction_error_deg']:.4f} deg (<= {TARGETS['direction_error_deg']:g}), "
          f"plane residual RMS {c['plane_residual_um']:.1f} um / max {c['plane_residual_max_um']:.1f} um "
          f"(< {TARGETS['plane_residual_um']:g}), SLSQP {c['solve_time_s']:.2f} s over {c['n_starts']} starts "
          f"({c['n_starts_at_best']} at the best residual)")
    return 0
