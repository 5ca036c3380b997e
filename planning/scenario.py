"""The `surgery` scenario: a phakic eye in front of the Meca500, entered through a trocar.

All positions in mm, in W (robot base) or E (eye frame, design.md) as their names say.

Eye placement X_WE (the choice and why). The instrument is straight and 92 mm long from
the flange, and the flange is 70 mm past the wrist centre, so the wrist centre sits
162 mm behind the tip along the shaft: pivoting the shaft about the trocar through the
cone of directions the work needs (about 40 deg about its mean for the spiral, about
70 deg for the peripheral band) swings the wrist centre over a cap of that radius. The
arm reaches the wrist centre between about 95 mm (J3 at 5 deg from its +70 deg limit) and
261 mm (stretched, elbow singular) from the shoulder (J2 axis, 135 mm above the base).
The distance shoulder -> wrist changes least over the cap when the trocar lies on the
line from the shoulder along the mean shaft direction; the spherical wrist (J4..J6 axes
meet at J5) stays clear of its J5 = 0 singularity when the forearm is well outside the
cone of shaft directions. `SURGERY_EYE_POSE` below is the placement found by a search over
these parameters that maximises the smallest joint margin over the whole spiral and the
share of the peripheral band reachable with margin; its comment gives the figures.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from models import Ellipsoid
from models.eyes import EyePose, make_eye
from models.scan.spiral import PAPER_PITCH_MM, PAPER_REVOLUTIONS, PAPER_SPACING_MM, archimedean_spiral
from models.shapes.validation import as_vector3
from planning.ports import port_p_EC

# Trocar on the pars plana, about 3.5-4 mm behind the limbus, 8 mm off the visual axis.
TROCAR_P_EC_MM = (8.0, 0.0, 7.2)
# Crystalline lens keep-out: on the axis, z in [5.8, 9.8] mm, radius 4.5 mm (eye.sdf).
LENS_CENTER_E_MM = (0.0, 0.0, 7.8)
LENS_RADII_MM = (4.5, 4.5, 2.0)
# The trocar must sit in the eye wall: within this distance of the retina (sclera,
# choroid and retina together are about 1 mm thick).
EYE_WALL_MM = 1.0
# Peripheral band: retina between the equator (z_E = 0) and the ora serrata, about 6 mm
# behind the limbus, i.e. about 2.2 mm behind the trocar's 3.5-4 mm: z_E = 5.0 mm.
ORA_SERRATA_Z_E_MM = 5.0
# Spiral plane: the coronal plane z_E = 0 (the paper's). Every beam from the trocar
# (z_E = 7.2) through a point of this plane descends, so it meets the retina behind the
# equator (posterior retina), and the spiral's 9 mm outer radius leaves >= 2.4 mm to the
# retina there.
SPIRAL_DEPTH_Z_E_MM = 0.0
# Tip targets must stay this far inside the retina, and the shaft this far from the lens.
TIP_CLEARANCE_MM = 0.5
LENS_CLEARANCE_MM = 0.5
# Default sensor calibration error (true vs nominal sensor pose, in S): the accuracy the
# plate calibration reaches (models.calibration: 20 um position, 0.1 deg beam direction).
SENSOR_OFFSET_S_MM = (0.02, 0.0, 0.0)
SENSOR_ROTVEC_S_RAD = (0.0, np.radians(0.1), 0.0)

# X_WE: eye centre 123 mm in front of the base and 80 mm above it; visual axis z_E tilted
# 23 deg from vertical towards the robot, z_E = (-0.378, -0.098, 0.921) in W (the head
# below and in front of a robot mounted at the level of the face). The spiral starts at
# about (-2, 38, 9, 6, 76, 0) deg (shoulder forward, elbow up, J5 > 0). Closed-form reach
# study (planning.closed_form, every 0.2 mm of the spiral; 24 x 3 band targets): smallest
# joint margin along the spiral 8.5 deg (J3; J5 10 deg), the wrist 32 deg or more from its
# J5 = 0 singularity; 79 % of the lens-clearing peripheral band targets reachable with
# >= 5 deg margin (the others, mostly near the trocar's side, need the second port).
# Found by differential evolution over the trocar's distance and elevation from the
# shoulder, the mean shaft direction and the eye's roll, then a local trade of J3 against
# J5 margin by moving the eye (it cannot be better than about 9 deg on both: the shaft's
# 80 deg cone over the spiral swings the wrist centre across ~200 mm).
SURGERY_EYE_POSE = EyePose(Rotation.from_rotvec([0.1554, -0.3715, -0.2814]).as_matrix(), np.array([123.1, 3.1, 80.5]))
# X_WE for the 3-port layout (planning.ports: working ports at 10 and 2 o'clock): the eye
# of SURGERY_EYE_POSE turned about its visual axis by PORTS_ROLL_DEG, i.e. the robot placed
# at another angle around the head (Inagaki et al. 2025 choose eye posture and robot pose
# together for trocar access). The roll is the one of a scan over -180..180 deg in 15 deg
# steps (planning.ports' reach study: each cell's reasons from both working ports) with the
# most band cells reachable from one working port or the other with >= 5 deg joint margin:
# -30 deg puts the 2 o'clock port where the reference trocar is in W (the spiral that
# builds the model is the reference one) and the 10 o'clock port 120 deg round the eye.
PORTS_ROLL_DEG = -30.0
PORTS_EYE_POSE = EyePose(SURGERY_EYE_POSE.R_WE @ Rotation.from_euler("z", PORTS_ROLL_DEG, degrees=True).as_matrix(),
                         SURGERY_EYE_POSE.p_WE.copy())


def default_trocar_E(eye_name: str, eye_params: dict | None = None) -> np.ndarray:
    """The trocar (mm, E) on the eye `eye_name` (with make_eye's shape parameters
    `eye_params`): TROCAR_P_EC_MM for the emmetropic eye; for another eye the point in the
    same direction from the centre at the same depth relative to that eye's retina (a
    longer myopic eye puts the pars plana further out)."""
    p = np.array(TROCAR_P_EC_MM)
    u = p / np.linalg.norm(p)
    eyes = {"emmetropic": make_eye("emmetropic"), eye_name: make_eye(eye_name, **(eye_params or {}))}
    radial = {name: float(np.linalg.norm(eye.surface_points(u[None])[0])) for name, eye in eyes.items()}
    return u * (np.linalg.norm(p) + radial[eye_name] - radial["emmetropic"])


class TrueSensorPose:
    """What a scenario with `sensor_offset_S_mm` (3,) mm and `sensor_rotvec_S_rad` (3,) rad,
    the calibration error of the true sensor in the nominal sensor frame S, answers."""

    @property
    def X_S_Strue(self) -> tuple[np.ndarray, np.ndarray]:
        """(R, p mm) of the true sensor frame in the nominal sensor frame S."""
        return Rotation.from_rotvec(self.sensor_rotvec_S_rad).as_matrix(), self.sensor_offset_S_mm.copy()


@dataclass(frozen=True, eq=False)
class SurgeryScenario(TrueSensorPose):
    """Eye pose X_WE, trocar p_EC (mm, E; default `default_trocar_E(eye_name)`), eye shape name and its
    shape parameters (make_eye's keywords, models.eyes.EYE_PARAMS), lens keep-out (E) and the
    true sensor pose's calibration error (offset mm and rotation vector rad, both in S).
    `ports` (planning.ports.Port, optional): the sclerotomies of a multi-port plan, each
    placed on this eye by planning.ports.port_p_EC (p_EC_of, p_WC_of by name); `p_EC` is
    the trocar the robot is built through (the one the model-building scan uses).

    Raises ValueError when a trocar is not in the eye wall (within EYE_WALL_MM of the
    retina) or the shaft at it would start inside the lens keep-out.
    """

    eye_pose: EyePose = SURGERY_EYE_POSE
    p_EC: np.ndarray | None = None
    eye_name: str = "emmetropic"
    eye_params: dict = field(default_factory=dict)
    sensor_offset_S_mm: np.ndarray = field(default_factory=lambda: np.array(SENSOR_OFFSET_S_MM))
    sensor_rotvec_S_rad: np.ndarray = field(default_factory=lambda: np.array(SENSOR_ROTVEC_S_RAD))
    ports: tuple = ()

    def __post_init__(self):
        if not isinstance(self.eye_pose, EyePose):
            raise ValueError(f"eye_pose must be a models.eyes.EyePose (X_WE), got {type(self.eye_pose).__name__}")
        if self.p_EC is None:
            object.__setattr__(self, "p_EC", default_trocar_E(self.eye_name, self.eye_params))
        for name in ("p_EC", "sensor_offset_S_mm", "sensor_rotvec_S_rad"):
            object.__setattr__(self, name, as_vector3(getattr(self, name), name))
        object.__setattr__(self, "_eye", make_eye(self.eye_name, self.eye_pose, **self.eye_params))
        object.__setattr__(self, "_lens_E", Ellipsoid(np.array(LENS_CENTER_E_MM), np.array(LENS_RADII_MM)))
        self._check_trocar(self.p_EC, "p_EC")
        reference = default_trocar_E(self.eye_name, self.eye_params)
        object.__setattr__(self, "_ports", {p.name: port_p_EC(self.eye_name, p, reference, self.eye_params)
                                            for p in self.ports})
        if len(self._ports) != len(self.ports):
            raise ValueError("ports must have distinct names")
        for port in self.ports:
            self._check_trocar(self._ports[port.name], f"port {port.name} ({port.clock_hour:g} o'clock, "
                                                        f"{port.limbus_mm:g} mm behind the limbus)")

    def _check_trocar(self, p_EC: np.ndarray, label: str) -> None:
        sd = float(self._eye.signed_distance(self.eye_pose.to_W(p_EC[None]))[0])
        if abs(sd) > EYE_WALL_MM:
            where = "outside the eye wall" if sd < 0 else "inside the vitreous, not in the wall"
            raise ValueError(f"{label} at {np.round(p_EC, 3)} mm is {where}: its distance to the retina is "
                             f"{-sd:+.3f} mm; a trocar must lie within {EYE_WALL_MM} mm of the retina")
        if float(self._lens_E.signed_distance(p_EC)[0]) > -LENS_CLEARANCE_MM:
            raise ValueError(f"{label} at {np.round(p_EC, 3)} mm is within {LENS_CLEARANCE_MM} mm of the lens keep-out")

    def p_EC_of(self, name: str) -> np.ndarray:
        """The trocar (mm, E) of the port `name`; ValueError naming the ports otherwise."""
        if name not in self._ports:
            raise ValueError(f"unknown port {name!r}: the ports are {', '.join(self._ports) or 'none'}")
        return self._ports[name].copy()

    def p_WC_of(self, name: str) -> np.ndarray:
        """The trocar (mm, W) of the port `name`."""
        return self.eye_pose.to_W(self.p_EC_of(name)[None])[0]

    @property
    def eye(self):
        """The ground-truth retina (models.eyes.Eye) placed in W."""
        return self._eye

    @property
    def p_WC(self) -> np.ndarray:
        """The trocar (RCM point) in W, mm."""
        return self.eye_pose.to_W(self.p_EC[None])[0]

    @property
    def lens_W(self) -> Ellipsoid:
        """The lens keep-out ellipsoid in W (signed distance > 0 inside the lens)."""
        return Ellipsoid(self.eye_pose.to_W(self._lens_E.center[None])[0], self._lens_E.radii, self.eye_pose.R_WE)

    def tip_targets_W(self, P_ET) -> np.ndarray:
        """(N, 3) W positions (mm) of tip targets P_ET (N, 3) given in E, after checking
        that each lies at least TIP_CLEARANCE_MM inside the retina and that the straight
        shaft from the trocar to it keeps LENS_CLEARANCE_MM from the lens keep-out."""
        P_E = np.asarray(P_ET, dtype=float)
        if P_E.ndim != 2 or P_E.shape[1] != 3 or not np.all(np.isfinite(P_E)):
            raise ValueError(f"P_ET must be a finite (N, 3) array of tip targets in E, mm; got shape {P_E.shape}")
        P_W = self.eye_pose.to_W(P_E)
        depth = self._eye.signed_distance(P_W)
        bad = np.flatnonzero(depth < TIP_CLEARANCE_MM)
        if bad.size:
            i = bad[0]
            raise ValueError(f"tip target {i} at p_ET = {np.round(P_E[i], 3)} mm is outside the eye or within "
                             f"{TIP_CLEARANCE_MM} mm of the retina (depth {depth[i]:+.3f} mm; need >= {TIP_CLEARANCE_MM})")
        clear = self.lens_clearance_mm(P_E)
        bad = np.flatnonzero(clear < LENS_CLEARANCE_MM)
        if bad.size:
            i = bad[0]
            raise ValueError(f"tip target {i} at p_ET = {np.round(P_E[i], 3)} mm: the shaft from the trocar passes "
                             f"{clear[i]:.3f} mm from the lens keep-out (need >= {LENS_CLEARANCE_MM} mm)")
        return P_W

    def lens_clearance_mm(self, P_ET, samples: int = 64) -> np.ndarray:
        """(N,) smallest distance (mm) from the lens keep-out of the straight shaft segment
        from the trocar to each tip target P_ET (N, 3) in E (sampled; < 0: crosses it)."""
        s = np.linspace(0.0, 1.0, samples)[None, :, None]
        P_E = np.asarray(P_ET, dtype=float)
        seg = self.p_EC + s * (P_E[:, None, :] - self.p_EC)
        return -self._lens_E.signed_distance(seg.reshape(-1, 3)).reshape(len(P_E), samples).max(axis=1)

    def spiral_E(self, pitch_mm: float = PAPER_PITCH_MM, revolutions: float = PAPER_REVOLUTIONS,
                 spacing_mm: float = PAPER_SPACING_MM) -> np.ndarray:
        """(N, 3) the paper's Archimedean spiral in E, centred on the visual axis in the
        coronal plane z_E = SPIRAL_DEPTH_Z_E_MM (mm)."""
        xy = archimedean_spiral(pitch_mm, revolutions, spacing_mm)
        return np.column_stack([xy, np.full(len(xy), SPIRAL_DEPTH_Z_E_MM)])

    def peripheral_band_E(self, n_azimuth: int = 24, n_rings: int = 3, inset_mm: float = 1.0) -> np.ndarray:
        """(M, 3) tip targets in E over the peripheral band (equator to ora serrata) of the
        scenario's retinal ellipsoid, `inset_mm` inside it along the radius, that the shaft can reach
        from the trocar without crossing the lens keep-out (the rest needs the second port)."""
        z = np.linspace(0.0, ORA_SERRATA_Z_E_MM, n_rings)
        az = np.linspace(0.0, 2.0 * np.pi, n_azimuth, endpoint=False)
        Z, A = np.meshgrid(z, az, indexing="ij")
        a, b, c = self._eye.radii
        s = np.sqrt(1.0 - (Z / c) ** 2)
        P = np.column_stack([(a * s * np.cos(A)).ravel(), (b * s * np.sin(A)).ravel(), Z.ravel()])
        P *= (1.0 - inset_mm / np.linalg.norm(P, axis=1))[:, None]
        return P[self.lens_clearance_mm(P) >= LENS_CLEARANCE_MM]
