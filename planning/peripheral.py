"""Peripheral vitrectomy planning: shave the vitreous base through the trocar.

The band is the retina between the equator (z_E = 0) and the ora serrata, taken from the
FITTED model (Sphere or Ellipsoid in W), never from the truth. It is cut into cells on
rings `spacing_mm` apart (the cutter's sweep width); each cell's shaving target sits
`standoff_mm` inside the model along its normal. A cell is reachable when:
- the straight shaft from the trocar to it keeps clear of the lens keep-out ("lens"),
- the cutter port (on the shaft's side) can face the retina: the shaft's angle to the
  surface leaves the port normal within `port_max_deg` of the surface normal ("port"),
- the arm reaches it through the trocar with every joint `min_margin_deg` from its
  limits (closed-form shaft IK, any branch; "reach");
- at that posture, and all along the timed path's way to it (checked every
  SHAFT_CHECK_DT_S), the shaft points the filter watches keep `boundary_mm` +
  SHAFT_SLACK_MM from the model ("shaft"), else the filter would hold the instrument
  back there (the shaft enters near the wall, and a model with a wide margin puts the
  boundary across it); the tip and port are placed by the standoff.
The path visits the reachable cells ring by ring, alternating direction (a serpentine),
each waypoint by RCM inverse kinematics seeded from the previous one with the roll that
turns the port to the retina; a shape-preserving joint cubic within the speed limits times it
(planning.scan). Units: mm, s, rad (deg where named); frame W unless `_E`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from planning.closed_form import shaft_ik
from planning.robot import Robot
from planning.scenario import LENS_CLEARANCE_MM, ORA_SERRATA_Z_E_MM
from planning.sweep import (MAX_JOINT_STEP_RAD, SHAFT_CHECK_DT_S, SHAFT_SLACK_MM, Sweep, lens_clearances_mm,  # noqa: F401
                            plan_sweep, port_roll_rad, shaft_clearances_mm)

REASONS = ("ok", "uncertain", "lens", "port", "reach", "shaft")
BOUNDARY_MM = 0.5  # the virtual boundary's d_safe: a standoff must leave room above it
# The port rule: the cutter port (a side window) faces the retina when its normal lies
# within this angle of the retina's normal, i.e. when the shaft meets the retina at most
# this steeply. Surgeons shave the vitreous base with the port turned towards the vitreous
# skirt next to the retina and the cutter held oblique, with the retina brought to it by
# scleral depression (S. Charles, "Principles and techniques of vitreoretinal surgery",
# Ryan's Retina, chapter 101; the eophtha.com beginner's guide to vitrectomy); no source
# gives a number. At 60 deg the window still presents half its area (cos 60 deg) to the
# retina; a parameter (BandSpec.port_max_deg, `vitreoguard plan --port-angle-deg`).
PORT_FACING_MAX_DEG = 60.0


SPACING_RANGE_MM = (0.2, 5.0)  # BandSpec.spacing_mm: ring and azimuth spacing (= sweep width)
STANDOFF_MAX_MM = 5.0  # BandSpec.standoff_mm's upper end
TIP_SPEED_RANGE_MM_S = (0.1, 20.0)  # BandSpec.tip_speed_mm_s


@dataclass(frozen=True)
class BandSpec:
    """Band z_E range (mm, eye frame), ring and azimuth spacing (= sweep width, mm),
    standoff inside the model (mm), port and joint-margin limits (deg), tip speed (mm/s),
    and `boundary_mm`: the clearance the safety filter keeps from this model (d_safe +
    the model's uncertainty margin), which the tip's standoff and the whole instrument
    must respect."""

    z_min_E: float = 0.0
    z_max_E: float = ORA_SERRATA_Z_E_MM
    spacing_mm: float = 1.0
    standoff_mm: float = 1.0
    port_max_deg: float = PORT_FACING_MAX_DEG
    min_margin_deg: float = 5.0
    tip_speed_mm_s: float = 5.0
    boundary_mm: float = BOUNDARY_MM

    def __post_init__(self):
        if not (np.isfinite(self.z_min_E) and np.isfinite(self.z_max_E) and self.z_min_E < self.z_max_E):
            raise ValueError(f"band z_E range must be finite with z_min < z_max, got ({self.z_min_E}, {self.z_max_E}) mm")
        if not (SPACING_RANGE_MM[0] <= self.spacing_mm <= SPACING_RANGE_MM[1]):
            raise ValueError(f"spacing_mm must be in [{SPACING_RANGE_MM[0]:g}, {SPACING_RANGE_MM[1]:g}] mm, "
                             f"got {self.spacing_mm}")
        if not (BOUNDARY_MM <= self.boundary_mm <= 4.0):
            raise ValueError(f"boundary_mm must be in [{BOUNDARY_MM}, 4] mm (d_safe + the model's and the calibration's margins), "
                             f"got {self.boundary_mm}")
        if not (self.standoff_mm > self.boundary_mm + 0.1 and self.standoff_mm <= STANDOFF_MAX_MM):
            raise ValueError(f"standoff_mm must be in ({self.boundary_mm + 0.1:g}, {STANDOFF_MAX_MM:g}] mm (the boundary "
                             f"is {self.boundary_mm:g} mm and the filter's margins need room), got {self.standoff_mm}")
        if not (0.0 < self.port_max_deg <= 90.0) or not (0.0 <= self.min_margin_deg < 45.0):
            raise ValueError("port_max_deg must be in (0, 90] and min_margin_deg in [0, 45) deg")
        if not (TIP_SPEED_RANGE_MM_S[0] <= self.tip_speed_mm_s <= TIP_SPEED_RANGE_MM_S[1]):
            lo, hi = TIP_SPEED_RANGE_MM_S
            raise ValueError(f"tip_speed_mm_s must be in [{lo:g}, {hi:g}] mm/s, got {self.tip_speed_mm_s}")


@dataclass(frozen=True, eq=False)
class Band:
    """Cells of the band on (n_rings, n_az) grids: azimuth (rad, E), ring z_E (mm),
    surface points and inward unit normals of the model, shaving targets (W, mm),
    the reason each cell is (not) reachable and its port angle (deg)."""

    azimuth: np.ndarray
    z_E: np.ndarray
    surface_W: np.ndarray
    normal_W: np.ndarray
    target_W: np.ndarray
    reason: np.ndarray
    port_deg: np.ndarray

    @property
    def reachable(self) -> np.ndarray:
        return self.reason == "ok"


def _model_normal(model, P: np.ndarray) -> np.ndarray:
    """Inward unit normals of the model at its surface points P (M, 3)."""
    return np.asarray(model.gradient(P), dtype=float)


def band_surface(model, eye_pose, spec: BandSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(azimuths (n_az,), ring z_E (n_rings,), surface points (n_rings, n_az, 3) W,
    inward normals) of the model between spec.z_min_E and spec.z_max_E: rays from the
    nominal eye centre, their elevation solved (secant) so each hit lies at its ring's z_E.
    ValueError when the band leaves the model."""
    c = eye_pose.p_WE
    reach = float(model.ray_cast(c[None], (eye_pose.R_WE @ np.array([0.0, 0.0, 1.0]))[None])[0])
    if not (np.isfinite(reach) and spec.z_max_E < reach - spec.standoff_mm and spec.z_min_E > -reach + spec.standoff_mm):
        raise ValueError(f"band z_E in [{spec.z_min_E}, {spec.z_max_E}] mm lies outside the model "
                         f"(it spans z_E = +-{reach:.2f} mm about the eye centre)")
    z = np.arange(spec.z_min_E, spec.z_max_E + 1e-9, spec.spacing_mm)
    equator = float(model.ray_cast(c[None], (eye_pose.R_WE @ np.array([1.0, 0.0, 0.0]))[None])[0])
    n_az = int(np.ceil(2 * np.pi * equator / spec.spacing_mm))
    az = np.linspace(0.0, 2 * np.pi, n_az, endpoint=False)
    A, Z = np.meshgrid(az, z)
    def hit(elev):
        U_E = np.stack([np.cos(elev) * np.cos(A), np.cos(elev) * np.sin(A), np.sin(elev)], axis=-1).reshape(-1, 3)
        U = U_E @ eye_pose.R_WE.T
        d = model.ray_cast(np.repeat(c[None], len(U), axis=0), U)
        P = c + d[:, None] * U
        return P.reshape(A.shape + (3,)), eye_pose.to_E(P)[:, 2].reshape(A.shape)
    e0, e1 = np.arcsin(np.clip(Z / equator, -1, 1)), np.arcsin(np.clip(Z / equator, -1, 1)) + 0.01
    _, z0 = hit(e0)
    P1, z1 = hit(e1)
    for _ in range(6):  # secant on the elevation: z_E(hit) = ring z
        e2 = e1 - (z1 - Z) * (e1 - e0) / np.where(np.abs(z1 - z0) > 1e-12, z1 - z0, 1e-12)
        e0, z0 = e1, z1
        e1 = e2
        P1, z1 = hit(e1)
    return az, z, P1, _model_normal(model, P1.reshape(-1, 3)).reshape(P1.shape)


def cell_reasons(robot: Robot, scenario, targets_W: np.ndarray, normals_W: np.ndarray, spec: BandSpec,
                 p_EC=None) -> tuple[np.ndarray, np.ndarray]:
    """(reason per cell (M,) in REASONS, port angle deg (M,)) for shaving targets (M, 3) W
    with inward normals, from the scenario's trocar (or the trocar p_EC in E)."""
    reasons, port, _ = cell_reach(robot, scenario, targets_W, normals_W, spec, p_EC)
    return reasons, port


def cell_reach(robot: Robot, scenario, targets_W: np.ndarray, normals_W: np.ndarray, spec: BandSpec,
               p_EC=None, model=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """cell_reasons' (reasons, port angles deg) and the smallest clearance (mm) of the
    watched shaft points from `model` at each cell's posture (the closed-form branch with
    the largest joint margin; inf where none or without a model). With a model, a cell
    whose shaving target lies within spec.boundary_mm + SHAFT_SLACK_MM of it is
    "uncertain" (a planning.field_model.FieldModel's uncertainty puts the filter's boundary
    there), one whose shaft comes that near "shaft" (the sweep's own check, at the cell)."""
    p_EC = scenario.p_EC if p_EC is None else np.asarray(p_EC, dtype=float)
    p_WC = scenario.eye_pose.to_W(p_EC[None])[0]
    U = targets_W - p_WC
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    port = np.degrees(np.arcsin(np.clip(np.abs(np.einsum("ij,ij->i", normals_W, U)), 0.0, 1.0)))
    lens = lens_clearances_mm(scenario.lens_W, p_WC, targets_W)
    margin = np.radians(spec.min_margin_deg)
    reasons = np.full(len(targets_W), "ok", dtype=object)
    shaft = np.full(len(targets_W), np.inf)
    near = (np.zeros(len(targets_W), dtype=bool) if model is None
            else np.asarray(model.signed_distance(targets_W), dtype=float) < spec.boundary_mm + SHAFT_SLACK_MM)
    for i, (t, u) in enumerate(zip(targets_W, U)):
        if near[i]:
            reasons[i] = "uncertain"
        elif lens[i] < LENS_CLEARANCE_MM:
            reasons[i] = "lens"
        elif port[i] > spec.port_max_deg:
            reasons[i] = "port"
        else:
            Q = shaft_ik(robot.arm, t, u)
            m = np.min(np.minimum(Q[:, :5] - robot.q_lower[:5], robot.q_upper[:5] - Q[:, :5]), axis=1) if len(Q) else []
            if not len(Q) or np.max(m) < margin:
                reasons[i] = "reach"
            elif model is not None:
                shaft[i] = shaft_clearances_mm(robot, Q[np.argmax(m)], p_WC, model)[0]
                if shaft[i] < spec.boundary_mm + SHAFT_SLACK_MM:
                    reasons[i] = "shaft"
    return reasons, port, shaft


def plan_band(robot: Robot, scenario, model, spec: BandSpec = BandSpec()) -> Band:
    """The band of `model` (W) with its shaving targets and reachability from the trocar."""
    az, z, S, N = band_surface(model, scenario.eye_pose, spec)
    T = S + spec.standoff_mm * N
    reasons, port = cell_reasons(robot, scenario, T.reshape(-1, 3), N.reshape(-1, 3), spec)
    return Band(az, z, S, N, T, reasons.reshape(S.shape[:2]), port.reshape(S.shape[:2]))


@dataclass(frozen=True, eq=False)
class Plan:
    """The shaving path: waypoints (K, 3) W, rolls (K,), joint trajectory q(t), the band,
    and the planning time (s)."""

    band: Band
    waypoints_W: np.ndarray
    roll_rad: np.ndarray
    trajectory: object  # pydrake PiecewisePolynomial, rad
    targets_used_W: np.ndarray
    plan_time_s: float


def serpentine(band: Band, mask=None, flip: bool = False) -> list[tuple[int, int]]:
    """The cells of `mask` (n_rings, n_az) bool (default: the reachable ones) as (ring,
    azimuth index) ring by ring, alternating direction (azimuth increasing on even rings,
    decreasing on odd ones; the other way round with `flip`, which gives the path its
    other pair of end cells). Each ring's cells start after its widest gap, so the path
    never sweeps across the cells left out."""
    order = []
    n_az = len(band.azimuth)
    mask = band.reachable if mask is None else np.asarray(mask, dtype=bool)
    for r in range(len(band.z_E)):
        ok = mask[r]
        if not ok.any():
            continue
        if ok.all():
            idx = list(range(n_az))
        else:
            start = _after_widest_gap(ok)
            idx = [(start + k) % n_az for k in range(n_az) if ok[(start + k) % n_az]]
        order += [(r, i) for i in (idx if (r + flip) % 2 == 0 else idx[::-1])]
    return order


def _after_widest_gap(ok: np.ndarray) -> int:
    """Index of the first reachable cell after the longest run of unreachable ones (cyclic)."""
    n = len(ok)
    best, best_end, run = -1, 0, 0
    for k in range(2 * n):
        if not ok[k % n]:
            run += 1
            if run > best:
                best, best_end = run, k % n
        else:
            run = 0
    return (best_end + 1) % n


def plan_path(robot: Robot, scenario, model, spec: BandSpec = BandSpec(), q_start=None) -> Plan:
    """Plan the shaving path over the reachable band of `model` from the scenario's trocar.
    Raises ValueError for a bad band or standoff and IKFailure when nothing is reachable."""
    t0 = time.perf_counter()
    band = plan_band(robot, scenario, model, spec)
    sweep = plan_sweep(robot, band, scenario.p_WC, model, spec, serpentine(band), q_start, scenario.lens_W)
    for cell, reason in sweep.dropped.items():
        band.reason[cell] = reason
    return Plan(band, sweep.targets_W, sweep.roll_rad, sweep.trajectory, sweep.targets_used_W, time.perf_counter() - t0)


def coverage(band: Band, path_W: np.ndarray, sweep_mm: float) -> float:
    """Fraction of the reachable cells' targets within sweep_mm / 2 of the tip path
    (polyline through path_W (K, 3) mm, sampled)."""
    T = band.target_W[band.reachable]
    if not len(T):
        return 0.0
    from scipy.spatial import cKDTree

    seg = np.diff(path_W, axis=0)
    n = np.maximum(np.ceil(np.linalg.norm(seg, axis=1) / (0.1 * sweep_mm)).astype(int), 1)
    dense = np.vstack([path_W[k] + np.linspace(0, 1, m, endpoint=False)[:, None] * seg[k] for k, m in enumerate(n)]
                      + [path_W[-1:]])
    d, _ = cKDTree(dense).query(T)
    return float(np.mean(d <= 0.5 * sweep_mm + 0.05 * sweep_mm))
