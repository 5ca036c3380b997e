"""The Meca500 with the vitrectomy instrument as a Drake MultibodyPlant.

Drake works in metres; this wrapper is the one place that converts: every argument and
result is in millimetres (positions), radians (joints) and mm/rad (Jacobians). Frames
(design.md): W robot base, F flange, I instrument (origin at F, x along the shaft), T
tip, S nominal sensor (z along the beam), P cutter port; with a scenario also E eye
(planning/data/eye.sdf welded at X_WE), C trocar (on the eye; the pivot in the air of a
planning.phantom scene) and S_true, the true sensor (S with the scenario's calibration
error).

Poses and Jacobians come from the plant's chain compiled once (planning.chain: a
product of exponentials read off the plant, held to it by tests): the 1 kHz loop asks
for several per step, and Drake's Python bindings cost 10-50 us a query.
"""
from __future__ import annotations

from importlib.resources import files

import numpy as np
from pydrake.geometry import Sphere
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
from pydrake.multibody.tree import FixedOffsetFrame
from pydrake.systems.framework import DiagramBuilder

from planning.chain import MM_PER_M, Chain, rigid_points
from planning.closed_form import arm_lengths

URDF = files("planning") / "data" / "meca500.urdf"
EYE_SDF = files("planning") / "data" / "eye.sdf"
FRAMES = {"F": "flange", "I": "instrument", "T": "tip", "S": "sensor", "P": "port"}
TROCAR_VISUAL_RADIUS_MM = 0.4
# RCM drift-correction gain: k dt = 0.2 at 1 kHz (stable, no overshoot); holds the RCM
# error of the spiral scan within 3 um at 5 mm/s (50/s: 11 um).
RCM_GAIN_PER_S = 200.0


class Robot:
    """Meca500 + instrument. `q` is always (6,) in rad; positions in mm; Jacobians mm/rad.

    `builder`, `plant` and `scene_graph` are exposed for diagrams that add more (the
    closed loop, Meshcat); the plant is finalized. With a `scenario`
    (planning.scenario.SurgeryScenario) the eye, the trocar C and the true sensor frame
    S_true are added and `p_WC` is the scenario's trocar.
    """

    def __init__(self, scenario=None, builder: DiagramBuilder | None = None):
        self.builder = DiagramBuilder() if builder is None else builder
        self.plant, self.scene_graph = AddMultibodyPlantSceneGraph(self.builder, 0.0)
        self.scenario = scenario
        Parser(self.plant).AddModels(str(URDF))
        self.plant.WeldFrames(self.plant.world_frame(), self.plant.GetFrameByName("base"))
        frames = dict(FRAMES)
        if scenario is not None:
            self._add_scenario(scenario)
            frames.update({"E": "eye", "C": "trocar", "S_true": "sensor_true"})
        self.plant.Finalize()
        self._frames = {k: self.plant.GetFrameByName(v) for k, v in frames.items()}
        self.chain = Chain(self.plant, self._frames)
        self.q_lower = self.plant.GetPositionLowerLimits().copy()
        self.q_upper = self.plant.GetPositionUpperLimits().copy()
        self.qdot_max = self.plant.GetVelocityUpperLimits().copy()
        self.arm = arm_lengths(self.chain)  # the closed form's lengths (planning.closed_form.shaft_ik)
        self.tip_offset_mm = self.arm.tip_offset_mm  # flange -> tip along the flange x axis
        # the cutter port P in the instrument frame I, mm (the plant's fixed offset, unrounded by W)
        X_IP = self._frames["P"].CalcPose(self.plant.CreateDefaultContext(), self._frames["I"])
        self.p_IP = MM_PER_M * X_IP.translation()

    def _add_scenario(self, scenario) -> None:
        """Weld the eye at X_WE, add the trocar frame C (with a small marker) on it and the
        true sensor frame on the instrument."""
        plant = self.plant
        (eye_model,) = Parser(plant).AddModels(str(EYE_SDF))
        eye = plant.GetFrameByName("eye", eye_model)
        X_WE = RigidTransform(RotationMatrix(scenario.eye_pose.R_WE), scenario.eye_pose.p_WE / MM_PER_M)
        plant.WeldFrames(plant.world_frame(), eye, X_WE)
        X_EC = RigidTransform(scenario.p_EC / MM_PER_M)
        plant.AddFrame(FixedOffsetFrame("trocar", eye, X_EC))
        plant.RegisterVisualGeometry(eye.body(), X_EC, Sphere(TROCAR_VISUAL_RADIUS_MM / MM_PER_M), "trocar",
                                     np.array([0.2, 0.8, 0.2, 1.0]))
        R, p = scenario.X_S_Strue
        plant.AddFrame(FixedOffsetFrame("sensor_true", plant.GetFrameByName("sensor"),
                                        RigidTransform(RotationMatrix(R), p / MM_PER_M)))

    @property
    def p_WC(self) -> np.ndarray:
        """The scenario's trocar in W, mm (ValueError without a scenario)."""
        if self.scenario is None:
            raise ValueError("p_WC needs a Robot built with a scenario")
        return self.scenario.p_WC

    @property
    def nq(self) -> int:
        return 6

    @staticmethod
    def checked_joint_angles(q) -> np.ndarray:
        """q as a (6,) float array of finite joint angles (rad); ValueError otherwise."""
        q = np.asarray(q, dtype=float)
        if q.shape != (6,):
            raise ValueError(f"q must have shape (6,) in rad, got {q.shape}")
        if not np.all(np.isfinite(q)):
            raise ValueError(f"q must be finite (rad), got {q}")
        return q

    def pose(self, frame: str, q) -> tuple[np.ndarray, np.ndarray]:
        """(R_W<frame> (3, 3), p_W<frame> (3,) mm) of frame F, I, T, S, P (and E, C,
        S_true with a scenario) at q."""
        return self.chain.pose(frame, self.checked_joint_angles(q))

    def point(self, frame: str, p_frame_mm, q) -> np.ndarray:
        """Position (3,) mm in W of a point fixed in `frame` at p_frame_mm (3,) mm."""
        R, p = self.pose(frame, q)
        return p + R @ np.asarray(p_frame_mm, dtype=float)

    def jacobian(self, frame: str, p_frame_mm, q) -> np.ndarray:
        """(3, 6) translational Jacobian, mm/rad, of the point p_frame_mm fixed in `frame`, in W."""
        R, p, J = self.pose_and_spatial_jacobian(frame, q)
        return rigid_points(R, p, J, np.asarray(p_frame_mm, dtype=float).reshape(1, 3))[1][0]

    def spatial_jacobian(self, frame: str, q) -> np.ndarray:
        """(6, 6) spatial Jacobian of `frame`'s origin in W at q: rows 0-2 angular (rad/rad),
        rows 3-5 translational (mm/rad). A point r_W (mm, from the origin) fixed in the frame
        moves with J_v - [r_W]x J_w: one call gives every point of a rigid body."""
        return self.pose_and_spatial_jacobian(frame, q)[2]

    def pose_and_spatial_jacobian(self, frame: str, q) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(R_W<frame>, p_W<frame> mm, spatial_jacobian) from one evaluation of the chain."""
        return self.chain.pose_and_jacobian(frame, self.checked_joint_angles(q))

    def shaft(self, q) -> tuple[np.ndarray, np.ndarray]:
        """(p_WI (3,) mm: a point on the shaft axis, u_W (3,): unit direction towards the tip)."""
        R, p = self.pose("I", q)
        return p, R[:, 0]

    def beam(self, q, true: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """(origin (3,) mm, unit direction (3,)) in W of the iiOCT beam: the nominal sensor
        S, or with `true` the scenario's true sensor S_true (calibration error applied)."""
        R, p = self.pose("S_true" if true else "S", q)
        return p, R[:, 2]

    def shaft_point_at_trocar(self, q, p_WC) -> tuple[np.ndarray, float]:
        """(p_WQ (3,) mm, lambda mm): the shaft-axis point Q nearest the trocar p_WC and its
        distance along the shaft from the flange; its Jacobian is jacobian("I", [lambda, 0, 0], q)."""
        p, u = self.shaft(q)
        lam = float(u @ (np.asarray(p_WC, dtype=float) - p))
        return p + lam * u, lam

    def rcm_error_mm(self, q, p_WC) -> float:
        """Distance (mm) of the trocar point p_WC from the shaft line at q."""
        R, p = self.pose("I", q)
        e = R[:, 1:].T @ (np.asarray(p_WC, dtype=float) - p)  # lateral coordinates in I
        return float(np.sqrt(e @ e))

    def rcm_rows(self, q, p_WC, gain_per_s: float = RCM_GAIN_PER_S) -> tuple[np.ndarray, np.ndarray]:
        """RCM equality rows (A (2, 6), b (2,) mm/s) with A qdot = b for qdot in rad/s: the
        material shaft point at the trocar moves only along the shaft (its velocity along
        the shaft's y and z axes is zero), and its lateral error e (mm) decays as
        de/dt = -gain_per_s e (drift correction)."""
        R, p, J_I = self.pose_and_spatial_jacobian("I", q)  # one evaluation of the chain
        d = np.asarray(p_WC, dtype=float) - p
        lam = float(R[:, 0] @ d)  # shaft coordinate of the trocar, mm
        N = R[:, 1:].T  # the two lateral directions of the shaft, rows
        J = rigid_points(R, p, J_I, np.array([[lam, 0.0, 0.0]]))[1][0]
        return N @ J, gain_per_s * (N @ d)

    def joint_margin_rad(self, q) -> np.ndarray:
        """(6,) distance of each joint to its nearer limit, rad (negative: beyond it)."""
        q = np.asarray(q, dtype=float)
        return np.minimum(q - self.q_lower, self.q_upper - q)
