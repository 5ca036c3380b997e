"""The `phantom` scenario: a printed lower half of an eye open on the bench, scanned from
above (the paper's bench set-up for its printed shapes: no trocar, no eye around it).

All positions in mm, in W (robot base) or E (the phantom's eye frame: origin at the
retina's centre, the rim on z_E = 0, the cup below it) as their names say.

The scan. The instrument looks into the cup from above: its tip moves over the paper's
Archimedean spiral in the plane z_E = PHANTOM_TIP_PLANE_Z_E_MM, 2 mm above the rim (the
shaft never enters the cup), and the shaft (and the beam along it) always passes through
the pivot p_EC = (0, 0, PHANTOM_PIVOT_Z_E_MM), a point in the air on the phantom's axis.
The pivot is no trocar: nothing holds the shaft there; it is the choice of beam direction
that makes the scan cover the lower half with a cone of shaft directions the arm can
reach. A tip at radius r in the tip plane tilts the beam by atan(r / 10 mm) from the
axis: the spiral's 9 mm outer radius gives 42 deg, whose beam meets the retina about
82 deg from the posterior pole (the rim is at 90 deg) at an incidence of about 40 deg;
at the pole the incidence is 0. The beam meets the retina 3.5 mm (rim) to 14 mm (pole)
from the tip: inside the fibre's axial range (models.iioct.OctEngine.max_distance_mm,
43 mm in water or vitreous) and about the surgery scan's range, where the confocal gate
still leaves the retina 10 dB or more over the noise. A higher pivot narrows the cone but
sees the walls more obliquely (incidence = polar angle - tilt), where the extractor's bias
grows (20 um at 50-60 deg, models.iioct.error_model).

Two passes. The tip goes out along the spiral with the instrument rolled to J6 = -90 deg,
stops, turns by 180 deg about its shaft (J6 alone: the tip and the shaft's line stay;
ROLL_TURN_S, a cosine profile) and comes back along the same spiral. The sensor's
calibration error is fixed in the instrument: its lateral parts (an offset across the
beam, a tilt of the beam) displace the points of the two passes in opposite directions,
so the registration, which places the mesh where the points are, sees them cancel to
first order instead of a rigid shift and tilt of the whole cloud.

The placement X_WE (`PHANTOM_EYE_POSE`: level, the cup's axis vertical, its centre 110 mm
in front of the robot, 11 mm to its right and 110 mm above its base: a phantom on a
stand). Found by differential evolution over the phantom's position (the cup's centre at
least 110 mm in front of the J1 axis, clear of the base) maximising, over the best
closed-form branch (planning.closed_form.shaft_ik), the smallest over the spiral (every
1 mm) of each joint's margin to its limits and of |J5| - 15 deg (the wrist's distance
from its singularity): 6.4 deg, J3 and J5 limiting equally (J5 no closer than 44 deg to
0). The shaft's 84 deg cone swings the wrist centre, 162 mm behind the tip, across about
220 mm: a cup tilted 10 deg towards the robot gains 1 deg of margin (7.5), a level one is
the bench's natural set-up. `scan_joint_margin_deg` measures a placement the same way.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from models.eyes import EyePose, make_eye
from models.scan.spiral import archimedean_spiral
from models.shapes.validation import as_vector3
from planning.scenario import SENSOR_OFFSET_S_MM, SENSOR_ROTVEC_S_RAD, TrueSensorPose

PHANTOM_TIP_PLANE_Z_E_MM = 2.0
PHANTOM_PIVOT_Z_E_MM = 12.0
PHANTOM_EYE_POSE = EyePose(np.eye(3), np.array([110.0, -11.0, 110.0]))
START_ROLL_RAD = -0.5 * np.pi  # J6 on the way out; +90 deg on the way back (J6's limits: +-180 deg)
ROLL_TURN_S = 1.0  # the half turn about the shaft between the passes: J6 peaks at 283 deg/s (limit 500)
WRIST_SINGULAR_DEG = 15.0  # |J5| below this counts as lost margin (the wrist's singularity at J5 = 0)


@dataclass(frozen=True, eq=False)
class PhantomScenario(TrueSensorPose):
    """A printed phantom (`eye_name`, make_eye's `eye_params`) placed at `eye_pose` (X_WE),
    scanned from above through the pivot p_EC (mm, E; module docstring), with the true
    sensor pose's calibration error (offset mm and rotation vector rad, in S) as in
    planning.SurgeryScenario. Answers what planning.Robot and planning.iioct.IioctSensor
    ask of a scenario (`eye`, `p_WC`, `X_S_Strue`, the tip targets `spiral_E`).

    Raises ValueError when the pivot is not above the tip plane on the cup's side."""

    eye_pose: EyePose = PHANTOM_EYE_POSE
    p_EC: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, PHANTOM_PIVOT_Z_E_MM]))
    eye_name: str = "emmetropic"
    eye_params: dict = field(default_factory=dict)
    sensor_offset_S_mm: np.ndarray = field(default_factory=lambda: np.array(SENSOR_OFFSET_S_MM))
    sensor_rotvec_S_rad: np.ndarray = field(default_factory=lambda: np.array(SENSOR_ROTVEC_S_RAD))

    def __post_init__(self):
        if not isinstance(self.eye_pose, EyePose):
            raise ValueError(f"eye_pose must be a models.eyes.EyePose (X_WE), got {type(self.eye_pose).__name__}")
        for name in ("p_EC", "sensor_offset_S_mm", "sensor_rotvec_S_rad"):
            object.__setattr__(self, name, as_vector3(getattr(self, name), name))
        if self.p_EC[2] <= PHANTOM_TIP_PLANE_Z_E_MM + 1.0:
            raise ValueError(f"p_EC (the pivot) at z_E = {self.p_EC[2]:g} mm must lie at least 1 mm above the tip "
                             f"plane z_E = {PHANTOM_TIP_PLANE_Z_E_MM:g} mm")
        object.__setattr__(self, "_eye", make_eye(self.eye_name, self.eye_pose, **self.eye_params))

    @property
    def eye(self):
        """The ground-truth retina (models.eyes.Eye) placed in W; the phantom is its
        lower half (z_E <= 0), which is all a beam from above the rim meets."""
        return self._eye

    @property
    def p_WC(self) -> np.ndarray:
        """The pivot in W, mm."""
        return self.eye_pose.to_W(self.p_EC[None])[0]

    def spiral_E(self, pitch_mm: float = 1.5, revolutions: float = 6.0, spacing_mm: float = 0.1) -> np.ndarray:
        """(N, 3) tip targets in E: the Archimedean spiral centred on the axis in the tip
        plane z_E = PHANTOM_TIP_PLANE_Z_E_MM (mm). ValueError when its outer radius leaves
        the beam through the pivot short of the retina's lower half."""
        xy = archimedean_spiral(pitch_mm, revolutions, spacing_mm)
        P = np.column_stack([xy, np.full(len(xy), PHANTOM_TIP_PLANE_Z_E_MM)])
        U = P - self.p_EC
        U /= np.linalg.norm(U, axis=1)[:, None]
        d = self._eye.ray_cast(self.eye_pose.to_W(P), U @ self.eye_pose.R_WE.T)
        if not np.all(np.isfinite(d) & (P[:, 2] + d * U[:, 2] < 0.0)):
            raise ValueError(f"the spiral's outer radius {pitch_mm * revolutions:g} mm tilts the beam past the rim: "
                             "its beam through the pivot would miss the phantom's lower half")
        return P


def scan_joint_margin_deg(robot, scenario: PhantomScenario, pitch_mm: float = 1.5, revolutions: float = 6.0,
                          spacing_mm: float = 1.0) -> float:
    """The placement's reach figure (module docstring), deg: over the closed-form branches
    of `robot` (planning.Robot) at the spiral's tip targets with the shaft through the
    pivot (J6 = 0), the largest of each branch's smallest joint margin and |J5| -
    WRIST_SINGULAR_DEG; negative when no branch reaches the whole spiral within them."""
    from planning.closed_form import shaft_ik

    P = scenario.eye_pose.to_W(scenario.spiral_E(pitch_mm, revolutions, spacing_mm))
    U = P - scenario.p_WC
    U /= np.linalg.norm(U, axis=1)[:, None]
    worst = np.full(8, np.inf)
    for p, u in zip(P, U):
        C = shaft_ik(robot.arm, p, u, 0.0)
        if not len(C):
            return -np.inf
        m = np.minimum(np.minimum(C - robot.q_lower, robot.q_upper - C).min(axis=1),
                       np.abs(C[:, 4]) - np.radians(WRIST_SINGULAR_DEG))
        worst = np.minimum(worst, m)
    return float(np.degrees(worst.max()))


def rolled(q) -> np.ndarray:
    """(6,) rad: the posture q with J6 at START_ROLL_RAD (J6 turns the instrument about its
    shaft: the tip and the beam's line stay where q puts them)."""
    out = np.array(q, dtype=float)
    out[5] = START_ROLL_RAD
    return out


def return_pass(robot, P_W, p_WC, q_end, speed_mm_s: float, rate_hz: float) -> np.ndarray:
    """(M, 6) rad at `rate_hz` after q_end (6,) rad, the end of the spiral P_W (N, 3) mm out:
    the half turn about the shaft (J6 + 180 deg over ROLL_TURN_S, a cosine profile), then
    the spiral back to its start at `speed_mm_s` with the shaft through p_WC
    (planning.scan.run_diffik)."""
    from planning.scan import run_diffik

    t = np.arange(1, int(round(ROLL_TURN_S * rate_hz)) + 1) / rate_hz
    turn = np.repeat(np.asarray(q_end, dtype=float)[None], len(t), axis=0)
    turn[:, 5] += 0.5 * np.pi * (1.0 - np.cos(np.pi * t / ROLL_TURN_S))
    back = run_diffik(robot, np.asarray(P_W)[::-1], p_WC, turn[-1], speed_mm_s, rate_hz=rate_hz)
    return np.vstack([turn, back.q[1:]])
