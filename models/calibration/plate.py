"""Geometric calibration of the iiOCT sensor pose in the flange frame from a flat plate.

The paper's procedure (after Sifferman et al., RA-L 2022): the robot holds the
instrument at many flange poses X_WF_i = (R_i, t_i) above a static plate and the
sensor measures the distance m_i to it along its beam. The measured point
q_i = R_i (p + m_i u) + t_i (mm, in W) lies on the plate, so the unknown sensor
origin p (mm, in F), unit beam direction u (in F), unit plate normal a (in W) and
plate offset d (mm) make every residual a^T q_i + d vanish. They are found with
SciPy's SLSQP under the equality constraints |u| = |a| = 1, from several starts.

Identifiability (why `sample_flange_poses` looks the way it does). With one plane,
a^T R_i p only varies with the pose through R_i^T a, the plate normal seen from
the flange; its constant part is absorbed by d. So:
- pure translations of the flange leave p unobservable; rolling the flange about
  the plate normal does too. The sampler tilts the beam away from the normal
  (uniform in solid angle over a cone, default half-angle 65 deg: a matte plate
  still scatters back at that incidence) and rolls the flange about the beam
  (uniform in [-pi, pi]), so R_i^T a sweeps a cone around -u and its variations
  span all three axes of F.
- the component of p along u trades against a common offset of the distances:
  it is seen only through the spread of cos(tilt), hence the wide cone. With
  20 um noise and 250 poses its Cramer-Rao bound is 13 um for a 45 deg cone,
  6.6 um for 60 deg, 4.3 um for 70 deg.
- a tilt of u trades against a lateral shift of p: the two are told apart only
  by the spread of the distances m_i, so the sampler spreads them uniformly over
  2-15 mm of the sensor's working range (the retina is 10-20 mm from the tip in
  the paper's scan); 2-10 mm would double the direction error.
With these defaults, random set-ups (300 um / 2 deg sensor error, 20 um noise;
bench/bench_calibration.py) give position errors of about 8 um median, 14 um at
the 95th percentile, and direction errors of 0.03 deg median, 0.07 deg at the
95th percentile. `calibrate_sensor` refuses pose sets that leave the unknowns
unobservable rather than return an arbitrary answer.
Sign conventions: (a, d) and (-a, -d) describe the same plane; the result's
normal points back towards the sensor (a^T R_i u < 0).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize
from scipy.spatial.transform import Rotation

from models.shapes.validation import as_points, as_positive, as_vector3


def _as_unit(v, name: str, tol: float = 1e-6) -> np.ndarray:
    """Return v as a (3,) unit vector (renormalised exactly); ValueError if |v| is not 1 within tol."""
    a = as_vector3(v, name)
    n = np.linalg.norm(a)
    if abs(n - 1.0) > tol:
        raise ValueError(f"{name} must be a unit vector (|{name}| = 1 within {tol:g}), got norm {n:.6g}")
    return a / n


def _frozen(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class SensorPose:
    """The iiOCT sensor in the flange frame F: origin `p_FS` (3,) mm, unit beam `u_F` (3,)."""

    p_FS: np.ndarray
    u_F: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "p_FS", _frozen(as_vector3(self.p_FS, "p_FS")))
        object.__setattr__(self, "u_F", _frozen(_as_unit(self.u_F, "u_F")))

    def origins_W(self, R_WF, p_WF) -> np.ndarray:
        """(N, 3) sensor origins in W (mm) for flange poses R_WF (N, 3, 3), p_WF (N, 3) mm."""
        return np.einsum("nij,j->ni", R_WF, self.p_FS) + p_WF

    def beams_W(self, R_WF) -> np.ndarray:
        """(N, 3) unit beam directions in W for flange rotations R_WF (N, 3, 3)."""
        return np.einsum("nij,j->ni", R_WF, self.u_F)

    def points_W(self, R_WF, p_WF, distances_mm) -> np.ndarray:
        """(N, 3) measured points in W (mm): origin + distance along the beam."""
        return self.origins_W(R_WF, p_WF) + np.asarray(distances_mm, dtype=float)[:, None] * self.beams_W(R_WF)


@dataclass(frozen=True, eq=False)
class Plane:
    """The plane {x : normal_W . x + offset_mm = 0} in W; `normal_W` unit, `offset_mm` mm."""

    normal_W: np.ndarray
    offset_mm: float

    def __post_init__(self):
        object.__setattr__(self, "normal_W", _frozen(_as_unit(self.normal_W, "normal_W")))
        off = float(self.offset_mm)
        if not np.isfinite(off):
            raise ValueError(f"offset_mm must be finite, got {self.offset_mm!r}")
        object.__setattr__(self, "offset_mm", off)

    def signed_distance(self, Q) -> np.ndarray:
        """(M,) signed distance (mm) of points Q (M, 3) mm in W; > 0 on the normal's side."""
        return as_points(Q, "Q") @ self.normal_W + self.offset_mm


def _perpendicular_unit(u: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A random unit vector perpendicular to the unit vector u."""
    while True:
        v = rng.normal(size=3)
        v -= (v @ u) * u
        n = np.linalg.norm(v)
        if n > 1e-6:
            return v / n


def offset_sensor_pose(nominal: SensorPose, offset_mm: float, tilt_rad: float, rng: np.random.Generator) -> SensorPose:
    """A sensor pose `offset_mm` (>= 0) from `nominal` in a random direction, its beam
    tilted by `tilt_rad` (>= 0) about a random axis perpendicular to the nominal beam."""
    for name, v in (("offset_mm", offset_mm), ("tilt_rad", tilt_rad)):
        if not np.isfinite(v) or v < 0:
            raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    axis = _perpendicular_unit(nominal.u_F, rng)
    u = Rotation.from_rotvec(axis * tilt_rad).apply(np.array(nominal.u_F))
    return SensorPose(nominal.p_FS + offset_mm * direction, u)


def _rotations_aligning(u: np.ndarray, B: np.ndarray) -> Rotation:
    """Minimal rotations taking the unit vector u to each unit row of B (N, 3)."""
    axis = np.cross(u, B)
    s = np.linalg.norm(axis, axis=1)
    angle = np.arctan2(s, B @ u)
    # antiparallel: any axis perpendicular to u does; parallel: angle 0, axis irrelevant
    fallback = np.cross(u, np.eye(3)[np.argmin(np.abs(u))])
    axis = np.where((s > 1e-12)[:, None], axis / np.maximum(s, 1e-300)[:, None], fallback / np.linalg.norm(fallback))
    return Rotation.from_rotvec(axis * angle[:, None])


def sample_flange_poses(
    n: int,
    sensor: SensorPose,
    plane: Plane,
    rng: np.random.Generator,
    max_tilt_deg: float = 65.0,
    distance_range_mm=(2.0, 15.0),
    half_width_mm: float = 20.0,
    centre_W=None,
) -> tuple[np.ndarray, np.ndarray]:
    """Random flange poses (R_WF (n, 3, 3), p_WF (n, 3) mm) that aim `sensor` at `plane`.

    Each pose points the beam against the plane normal tilted by an angle uniform
    over the cone of half-angle `max_tilt_deg` (uniform in solid angle), rolls the
    flange about the beam uniformly, hits the plane within +-`half_width_mm` of
    `centre_W` (mm, projected onto the plane; default: its point nearest the W origin), and places the sensor origin at a distance along the
    beam uniform in `distance_range_mm`. A stand-in for robot poses until the
    Meca500 plant provides reachable ones; the module docstring explains the spread.
    """
    if int(n) != n or n < 1:
        raise ValueError(f"n must be a positive integer, got {n!r}")
    n = int(n)
    tilt_max = np.radians(as_positive(max_tilt_deg, "max_tilt_deg"))
    if tilt_max >= np.pi / 2:
        raise ValueError(f"max_tilt_deg must be in (0, 90), got {max_tilt_deg!r}")
    lo, hi = (float(x) for x in distance_range_mm)
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo <= hi):
        raise ValueError(f"distance_range_mm must be (lo, hi) with 0 < lo <= hi, got {distance_range_mm!r}")
    half = as_positive(half_width_mm, "half_width_mm")
    a = plane.normal_W
    e1 = _perpendicular_unit(a, rng)
    e2 = np.cross(a, e1)
    cos_t = rng.uniform(np.cos(tilt_max), 1.0, n)
    sin_t = np.sqrt(1.0 - cos_t**2)
    phi = rng.uniform(-np.pi, np.pi, n)
    B = -cos_t[:, None] * a + sin_t[:, None] * (np.outer(np.cos(phi), e1) + np.outer(np.sin(phi), e2))
    roll = Rotation.from_rotvec(B * rng.uniform(-np.pi, np.pi, n)[:, None])
    R_WF = (roll * _rotations_aligning(sensor.u_F, B)).as_matrix()
    c = np.zeros(3) if centre_W is None else as_vector3(centre_W, "centre_W")
    hit = c - plane.signed_distance(c)[0] * a + np.outer(rng.uniform(-half, half, n), e1) + np.outer(rng.uniform(-half, half, n), e2)
    m = rng.uniform(lo, hi, n)
    p_WF = hit - m[:, None] * B - np.einsum("nij,j->ni", R_WF, sensor.p_FS)
    return R_WF, p_WF


def _as_flange_poses(R_WF, p_WF) -> tuple[np.ndarray, np.ndarray]:
    R = np.asarray(R_WF, dtype=float)
    t = as_points(p_WF, "p_WF")
    if R.ndim != 3 or R.shape[1:] != (3, 3) or len(R) != len(t):
        raise ValueError(f"R_WF must be (N, 3, 3) matching p_WF (N, 3), got {R.shape} and {t.shape}")
    if not np.all(np.isfinite(R)):
        raise ValueError("R_WF contains NaN or inf")
    err = np.max(np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)))
    if err > 1e-8:
        raise ValueError(f"R_WF are not rotations: max |R^T R - I| = {err:.3g} > 1e-8")
    return R, t


def plate_distances(R_WF, p_WF, sensor: SensorPose, plane: Plane, noise_um: float = 0.0, rng=None) -> np.ndarray:
    """(N,) distances (mm) the sensor measures to `plane` from flange poses (R_WF, p_WF):
    the exact ray/plane intersection plus N(0, noise_um) noise (um, >= 0; `rng` needed if > 0).

    Raises ValueError if a beam points away from the plane or is parallel to it.
    """
    R, t = _as_flange_poses(R_WF, p_WF)
    if not np.isfinite(noise_um) or noise_um < 0:
        raise ValueError(f"noise_um must be finite and >= 0, got {noise_um!r}")
    along = sensor.beams_W(R) @ plane.normal_W
    height = plane.signed_distance(sensor.origins_W(R, t))
    with np.errstate(divide="ignore", invalid="ignore"):
        m = -height / along
    bad = ~(np.abs(along) > 1e-9) | ~(m > 0)
    if np.any(bad):
        raise ValueError(f"{int(bad.sum())} of {len(m)} beams do not reach the plane (pointing away or parallel)")
    if noise_um > 0:
        if rng is None:
            raise ValueError("rng is required when noise_um > 0")
        m = m + rng.normal(0.0, noise_um * 1e-3, len(m))
    return m


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Recovered `sensor` pose in F and `plane` in W; `residuals_mm` (N,) are the signed
    point-to-plane distances of the measured points; `n_starts` SLSQP runs took
    `solve_time_s`, `n_at_best` of them ended at the best residual (within 1e-6
    relative) and `converged` tells whether SLSQP reported success for the best one."""

    sensor: SensorPose
    plane: Plane
    residuals_mm: np.ndarray
    n_starts: int
    n_at_best: int
    converged: bool
    solve_time_s: float

    @property
    def residual_rms_um(self) -> float:
        return float(1e3 * np.sqrt(np.mean(self.residuals_mm**2)))

    @property
    def residual_max_um(self) -> float:
        return float(1e3 * np.max(np.abs(self.residuals_mm)))


class _PlateProblem:
    """Residuals a^T (R_i (p + m_i u) + t_i) + d and their Jacobian for x = [p, u, a, d].

    W is shifted to the centroid of the flange positions, which keeps d small and the
    problem well conditioned whatever the robot's base frame; `plane_in_W` undoes it.
    """

    def __init__(self, R, t, m):
        self.R, self.m = R, m
        self.centre = t.mean(axis=0)
        self.t = t - self.centre

    def points(self, p, u) -> np.ndarray:
        return np.einsum("nij,nj->ni", self.R, p + self.m[:, None] * u) + self.t

    def residuals(self, x) -> np.ndarray:
        return self.points(x[0:3], x[3:6]) @ x[6:9] + x[9]

    def jacobian(self, x) -> np.ndarray:
        Rta = np.einsum("nji,j->ni", self.R, x[6:9])  # R_i^T a
        return np.column_stack([Rta, self.m[:, None] * Rta, self.points(x[0:3], x[3:6]), np.ones(len(self.m))])

    def objective(self, x):
        """Mean squared residual in um^2 and its gradient."""
        r = self.residuals(x) * 1e3
        J = self.jacobian(x) * 1e3
        return r @ r / len(r), 2.0 * J.T @ r / len(r)

    def linear_start(self, u, a) -> np.ndarray:
        """x with the given u, a and the least-squares p, d (the residual is linear in them)."""
        Rta = np.einsum("nji,j->ni", self.R, a)
        A = np.column_stack([Rta, np.ones(len(self.m))])
        b = -(self.m * (Rta @ u) + self.t @ a)
        sol = np.linalg.lstsq(A, b, rcond=None)[0]
        return np.concatenate([sol[:3], u, a, sol[3:]])

    def plane_in_W(self, a, d) -> Plane:
        return Plane(a, d - a @ self.centre)

    def is_observable(self, x) -> bool:
        """Whether the residual Jacobian restricted to |u| = |a| = 1 has full rank (8) at x."""
        def tangent(v):  # two unit vectors spanning the plane perpendicular to v
            e = np.eye(3)[np.argmin(np.abs(v))]
            t1 = np.cross(v, e) / np.linalg.norm(np.cross(v, e))
            return np.column_stack([t1, np.cross(v, t1)])

        P = np.zeros((10, 8))
        P[0:3, 0:3] = np.eye(3)
        P[3:6, 3:5] = tangent(x[3:6])
        P[6:9, 5:7] = tangent(x[6:9])
        P[9, 7] = 1.0
        sv = np.linalg.svd(self.jacobian(x) @ P, compute_uv=False)
        return bool(sv[-1] > 1e-9 * sv[0])


_AXES = np.vstack([np.eye(3), -np.eye(3)])


def calibrate_sensor(R_WF, p_WF, distances_mm, plane_normal_starts=None) -> CalibrationResult:
    """Recover the sensor pose in F (and the plate in W) from plate distances.

    R_WF (N, 3, 3), p_WF (N, 3) mm: flange poses; distances_mm (N,): measured
    distances, N >= 10 (there are 8 degrees of freedom). SLSQP minimises the mean
    squared point-to-plane residual with |u| = |a| = 1 as equality constraints,
    started from u along +-x, +-y, +-z crossed with each row of
    `plane_normal_starts` ((K, 3), default the x, y, z axes of W; a's sign is
    immaterial); p and d start at their linear least-squares values for that (u, a).
    The start with the smallest residual wins. Raises ValueError if the poses leave
    p, u or the plane unobservable (e.g. the flange only translates).
    """
    R, t = _as_flange_poses(R_WF, p_WF)
    m = np.asarray(distances_mm, dtype=float)
    if m.shape != (len(t),) or not np.all(np.isfinite(m)):
        raise ValueError(f"distances_mm must be ({len(t)},) finite values in mm, got shape {m.shape}")
    if len(m) < 10:
        raise ValueError(f"calibration needs at least 10 poses, got {len(m)}")
    normals = np.eye(3) if plane_normal_starts is None else np.atleast_2d(np.asarray(plane_normal_starts, dtype=float))
    if normals.ndim != 2 or normals.shape[1] != 3 or not np.all(np.linalg.norm(normals, axis=1) > 0):
        raise ValueError("plane_normal_starts must be (K, 3) non-zero directions")
    normals = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    problem = _PlateProblem(R, t, m)
    constraints = [
        {"type": "eq", "fun": lambda x: x[3:6] @ x[3:6] - 1.0, "jac": lambda x: np.r_[0, 0, 0, 2 * x[3:6], 0, 0, 0, 0]},
        {"type": "eq", "fun": lambda x: x[6:9] @ x[6:9] - 1.0, "jac": lambda x: np.r_[0, 0, 0, 0, 0, 0, 2 * x[6:9], 0]},
    ]
    t0 = time.perf_counter()
    runs = [
        minimize(problem.objective, problem.linear_start(u0, a0), jac=True, method="SLSQP",
                 constraints=constraints, options={"maxiter": 500, "ftol": 1e-12})
        for u0 in _AXES for a0 in normals
    ]
    elapsed = time.perf_counter() - t0
    best = min(runs, key=lambda r: r.fun)
    x = best.x
    u, a = x[3:6] / np.linalg.norm(x[3:6]), x[6:9] / np.linalg.norm(x[6:9])
    d = x[9]
    if np.mean(np.einsum("nij,j->ni", R, u) @ a) > 0:  # make the normal face the sensor
        a, d = -a, -d
    x = np.concatenate([x[0:3], u, a, [d]])
    if not problem.is_observable(x):
        raise ValueError("the flange poses leave the sensor pose unobservable: vary the orientation "
                         "(tilt and roll relative to the plate) and the distance across the poses")
    n_at_best = sum(r.fun <= best.fun + 1e-6 * max(best.fun, 1.0) for r in runs)  # um^2
    return CalibrationResult(SensorPose(x[0:3], u), problem.plane_in_W(a, d), problem.residuals(x),
                             len(runs), int(n_at_best), bool(best.success), elapsed)


def position_error_um(estimate: SensorPose, truth: SensorPose) -> float:
    """Distance (um) between two sensor origins."""
    return float(1e3 * np.linalg.norm(estimate.p_FS - truth.p_FS))


def direction_error_deg(estimate: SensorPose, truth: SensorPose) -> float:
    """Angle (deg) between two beam directions."""
    c = np.cross(estimate.u_F, truth.u_F)
    return float(np.degrees(np.arctan2(np.linalg.norm(c), estimate.u_F @ truth.u_F)))
