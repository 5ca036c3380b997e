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
turns the port to the retina; a C2 joint spline within the speed limits times it
(planning.scan). Units: mm, s, rad (deg where named); frame W unless `_E`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from planning.closed_form import shaft_ik
from planning.ik import IKFailure, rcm_ik, signed_angle
from planning.instrument_points import instrument_points
from planning.robot import Robot
from planning.scan import plan_ik_scan, start_posture
from planning.scenario import LENS_CLEARANCE_MM, ORA_SERRATA_Z_E_MM

REASONS = ("ok", "lens", "port", "reach", "shaft")
BOUNDARY_MM = 0.5  # the virtual boundary's d_safe: a standoff must leave room above it
SHAFT_SLACK_MM = 0.2  # monitored points plan this far outside the boundary (the filter stays out)
MAX_JOINT_STEP_RAD = 1.0  # between neighbouring cells (1 mm apart): more is a branch change
SHAFT_CHECK_DT_S = 0.005  # the timed path's shaft check: the shaft moves < 0.05 mm between samples at 10 mm/s


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
    port_max_deg: float = 30.0
    min_margin_deg: float = 5.0
    tip_speed_mm_s: float = 5.0
    boundary_mm: float = BOUNDARY_MM

    def __post_init__(self):
        if not (np.isfinite(self.z_min_E) and np.isfinite(self.z_max_E) and self.z_min_E < self.z_max_E):
            raise ValueError(f"band z_E range must be finite with z_min < z_max, got ({self.z_min_E}, {self.z_max_E}) mm")
        if not (0.2 <= self.spacing_mm <= 5.0):
            raise ValueError(f"spacing_mm must be in [0.2, 5] mm, got {self.spacing_mm}")
        if not (BOUNDARY_MM <= self.boundary_mm <= 4.0):
            raise ValueError(f"boundary_mm must be in [{BOUNDARY_MM}, 4] mm (d_safe + the model's margin), "
                             f"got {self.boundary_mm}")
        if not (self.standoff_mm > self.boundary_mm + 0.1 and self.standoff_mm <= 5.0):
            raise ValueError(f"standoff_mm must be in ({self.boundary_mm + 0.1:g}, 5] mm (the boundary is "
                             f"{self.boundary_mm:g} mm and the filter's margins need room), got {self.standoff_mm}")
        if not (0.0 < self.port_max_deg <= 90.0) or not (0.0 <= self.min_margin_deg < 45.0):
            raise ValueError("port_max_deg must be in (0, 90] and min_margin_deg in [0, 45) deg")
        if not (0.1 <= self.tip_speed_mm_s <= 20.0):
            raise ValueError(f"tip_speed_mm_s must be in [0.1, 20] mm/s, got {self.tip_speed_mm_s}")


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
    p_EC = scenario.p_EC if p_EC is None else np.asarray(p_EC, dtype=float)
    p_WC = scenario.eye_pose.to_W(p_EC[None])[0]
    U = targets_W - p_WC
    U /= np.linalg.norm(U, axis=1, keepdims=True)
    port = np.degrees(np.arcsin(np.clip(np.abs(np.einsum("ij,ij->i", normals_W, U)), 0.0, 1.0)))
    lens = _lens_clearance(scenario, p_EC, scenario.eye_pose.to_E(targets_W))
    margin = np.radians(spec.min_margin_deg)
    reasons = np.full(len(targets_W), "ok", dtype=object)
    for i, (t, u) in enumerate(zip(targets_W, U)):
        if lens[i] < LENS_CLEARANCE_MM:
            reasons[i] = "lens"
        elif port[i] > spec.port_max_deg:
            reasons[i] = "port"
        else:
            Q = shaft_ik(robot.arm, t, u)
            ok = len(Q) and np.any(np.min(np.minimum(Q[:, :5] - robot.q_lower[:5], robot.q_upper[:5] - Q[:, :5]), axis=1) >= margin)
            if not ok:
                reasons[i] = "reach"
    return reasons, port


def _lens_clearance(scenario, p_EC: np.ndarray, P_E: np.ndarray, samples: int = 32) -> np.ndarray:
    """(M,) smallest distance (mm) of the straight shaft trocar -> P_E from the lens keep-out."""
    s = np.linspace(0.0, 1.0, samples)[None, :, None]
    seg = p_EC + s * (P_E[:, None, :] - p_EC)
    lens_E = scenario._lens_E
    return -lens_E.signed_distance(seg.reshape(-1, 3)).reshape(len(P_E), samples).max(axis=1)


def plan_band(robot: Robot, scenario, model, spec: BandSpec = BandSpec()) -> Band:
    """The band of `model` (W) with its shaving targets and reachability from the trocar."""
    az, z, S, N = band_surface(model, scenario.eye_pose, spec)
    T = S + spec.standoff_mm * N
    reasons, port = cell_reasons(robot, scenario, T.reshape(-1, 3), N.reshape(-1, 3), spec)
    return Band(az, z, S, N, T, reasons.reshape(S.shape[:2]), port.reshape(S.shape[:2]))


def port_roll_rad(p_WT: np.ndarray, p_WC: np.ndarray, normal_in_W: np.ndarray) -> float:
    """Roll about the shaft (planning.ik.roll_direction_W convention) that turns the
    cutter port (on the instrument's -y side) toward the retina (outward normal)."""
    u = (p_WT - p_WC) / np.linalg.norm(p_WT - p_WC)
    h = np.cross([0.0, 0.0, 1.0], u)
    h /= np.linalg.norm(h)
    out = -normal_in_W
    m = out - (out @ u) * u
    y = -m / np.linalg.norm(m)  # the port is at -y: y points away from the retina
    return signed_angle(h, y, u)


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


def serpentine(band: Band) -> list[tuple[int, int]]:
    """Reachable cells (ring, azimuth index) ring by ring, alternating direction. Each
    ring's reachable cells start after its widest unreachable gap, so the path never
    sweeps across the unreachable side."""
    order = []
    n_az = len(band.azimuth)
    for r in range(len(band.z_E)):
        ok = band.reachable[r]
        if not ok.any():
            continue
        if ok.all():
            idx = list(range(n_az))
        else:
            start = _after_widest_gap(ok)
            idx = [(start + k) % n_az for k in range(n_az) if ok[(start + k) % n_az]]
        order += [(r, i) for i in (idx if r % 2 == 0 else idx[::-1])]
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


def shaft_clearances_mm(robot: Robot, Q, p_WC, model) -> np.ndarray:
    """(K,) smallest clearance (mm, inside > 0) from `model` of the shaft points the safety
    filter watches at each posture Q (K, 6) rad (planning.instrument_points: past the
    trocar, behind the tip and port, which the standoff places); inf at a posture where
    none is that deep."""
    Q = np.atleast_2d(np.asarray(Q, dtype=float))
    shaft = [ip.P_W[[k for k, name in enumerate(ip.names) if name.startswith("shaft")]]
             for ip in (instrument_points(robot, q, p_WC) for q in Q)]
    owner = np.repeat(np.arange(len(Q)), [len(P) for P in shaft])
    out = np.full(len(Q), np.inf)
    if len(owner):
        np.minimum.at(out, owner, np.asarray(model.signed_distance(np.vstack(shaft)), dtype=float))
    return out


def _cells_too_near_on_the_way(robot: Robot, traj, P_used: np.ndarray, P_cells: np.ndarray, p_WC, model,
                               limit_mm: float) -> np.ndarray:
    """Indices into P_cells (K, 3) of the cells on whose way (from the previous waypoint of
    the timed joint trajectory, sampled every SHAFT_CHECK_DT_S) or at whose posture a
    watched shaft point comes within `limit_mm` of the model. P_used (M, 3): the targets
    of the trajectory's knots, P_cells in order among them (plan_ik_scan adds midpoints)."""
    knots = np.asarray(traj.get_segment_times())
    cell_knot = np.empty(len(P_cells), dtype=int)
    j = 0
    for k, p in enumerate(P_cells):  # the midpoints lie between the cells' rows
        while not np.array_equal(P_used[j], p):
            j += 1
        cell_knot[k] = j
    ts = np.union1d(np.arange(knots[0], knots[-1], SHAFT_CHECK_DT_S), knots)
    near = ts[shaft_clearances_mm(robot, traj.vector_values(ts).T, p_WC, model) < limit_mm]
    # a sample belongs to the first cell reached at or after it
    return np.unique(np.searchsorted(knots[cell_knot], near - 1e-12, side="left"))


def plan_path(robot: Robot, scenario, model, spec: BandSpec = BandSpec(), q_start=None) -> Plan:
    """Plan the shaving path over the reachable band of `model`. Raises ValueError for a
    bad band or standoff and IKFailure when nothing is reachable."""
    t0 = time.perf_counter()
    band = plan_band(robot, scenario, model, spec)
    cells = serpentine(band)
    limit = spec.boundary_mm + SHAFT_SLACK_MM
    q = q_start
    kept, Q = [], []
    for r, i in cells:  # RCM IK with the port's roll, seeded along the path; a failing cell is "reach"
        t, n = band.target_W[r, i], band.normal_W[r, i]
        try:
            seed = start_posture(robot, t, scenario.p_WC) if q is None else q
            q = rcm_ik(robot, t, scenario.p_WC, seed, roll_rad=port_roll_rad(t, scenario.p_WC, n))
        except IKFailure:
            band.reason[r, i] = "reach"
            continue
        jump = np.abs(q - Q[-1]).max() if Q else 0.0
        if np.min(robot.joint_margin_rad(q)) < np.radians(spec.min_margin_deg) or jump > MAX_JOINT_STEP_RAD:
            band.reason[r, i] = "reach"  # beyond the margins, or only on another branch (no continuous path)
            q = Q[-1] if Q else None
            continue
        # at the cell and on the way there (a first, cheap look: the joint spline runs close
        # to the straight line in joint space between neighbouring waypoints)
        on_way = [q] + ([Q[-1] + f * (q - Q[-1]) for f in (0.25, 0.5, 0.75)] if Q else [])
        if shaft_clearances_mm(robot, on_way, scenario.p_WC, model).min() < limit:
            band.reason[r, i] = "shaft"
            q = Q[-1] if Q else None
            continue
        kept.append((r, i))
        Q.append(q)
    while True:  # the timed trajectory, densely: drop the cells whose way in still nears the boundary
        if not kept:
            raise IKFailure("no cell of the band is reachable from this trocar")
        P = np.array([band.target_W[r, i] for r, i in kept])
        roll = np.array([port_roll_rad(band.target_W[r, i], scenario.p_WC, band.normal_W[r, i]) for r, i in kept])
        traj, P_used, _ = plan_ik_scan(robot, P, scenario.p_WC, spec.tip_speed_mm_s, roll_rad=roll, Q_waypoints=Q)
        bad = _cells_too_near_on_the_way(robot, traj, P_used, P, scenario.p_WC, model, limit)
        if not len(bad):
            break
        for k in bad:
            band.reason[kept[k]] = "shaft"
        keep = np.setdiff1d(np.arange(len(kept)), bad)
        kept, Q = [kept[k] for k in keep], [Q[k] for k in keep]
    return Plan(band, P, roll, traj, P_used, time.perf_counter() - t0)


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


def second_trocar(robot: Robot, scenario, band: Band, spec: BandSpec, n_candidates: int = 12) -> dict:
    """The trocar on the pars plana circle (same height and radius as the scenario's, other
    azimuths) that reaches the most of the cells this trocar cannot: its azimuth (deg) and
    the fraction of the band it adds."""
    missing = ~band.reachable
    T, N = band.target_W[missing], band.normal_W[missing]
    if not len(T):
        return {"azimuth_deg": None, "adds_fraction": 0.0}
    p = scenario.p_EC
    r, z, a0 = np.hypot(p[0], p[1]), p[2], np.arctan2(p[1], p[0])
    best = (None, 0)
    for a in a0 + np.linspace(0, 2 * np.pi, n_candidates, endpoint=False)[1:]:
        cand = np.array([r * np.cos(a), r * np.sin(a), z])
        reasons, _ = cell_reasons(robot, scenario, T, N, spec, p_EC=cand)
        n_ok = int(np.sum(reasons == "ok"))
        if n_ok > best[1]:
            best = (float(np.degrees(a) % 360.0), n_ok)
    return {"azimuth_deg": best[0], "adds_fraction": best[1] / band.reason.size}
