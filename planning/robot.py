"""The Meca500 with the vitrectomy instrument as a Drake MultibodyPlant.

Drake works in metres; this wrapper is the one place that converts: every argument and
result is in millimetres (positions), radians (joints) and mm/rad (Jacobians). Frames
(design.md): W robot base, F flange, I instrument (origin at F, x along the shaft), T
tip, S sensor (z along the beam), P cutter port.
"""
from __future__ import annotations

from importlib.resources import files

import numpy as np
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
from pydrake.multibody.tree import JacobianWrtVariable
from pydrake.systems.framework import DiagramBuilder

URDF = files("planning") / "data" / "meca500.urdf"
FRAMES = {"F": "flange", "I": "instrument", "T": "tip", "S": "sensor", "P": "port"}
MM_PER_M = 1000.0


class Robot:
    """Meca500 + instrument. `q` is always (6,) in rad; positions in mm; Jacobians mm/rad.

    `builder`, `plant` and `scene_graph` are exposed for diagrams that add more (the
    closed loop, Meshcat); `finalize()` has been called on the plant.
    """

    def __init__(self, builder: DiagramBuilder | None = None):
        self.builder = DiagramBuilder() if builder is None else builder
        self.plant, self.scene_graph = AddMultibodyPlantSceneGraph(self.builder, 0.0)
        Parser(self.plant).AddModels(str(URDF))
        self.plant.WeldFrames(self.plant.world_frame(), self.plant.GetFrameByName("base"))
        self.plant.Finalize()
        self._context = self.plant.CreateDefaultContext()
        self._frames = {k: self.plant.GetFrameByName(v) for k, v in FRAMES.items()}
        self.q_lower = self.plant.GetPositionLowerLimits().copy()
        self.q_upper = self.plant.GetPositionUpperLimits().copy()
        self.qdot_max = self.plant.GetVelocityUpperLimits().copy()
        self._q = np.full(6, np.nan)

    @property
    def nq(self) -> int:
        return 6

    def _set(self, q) -> None:
        q = np.asarray(q, dtype=float)
        if q.shape != (6,):
            raise ValueError(f"q must have shape (6,) in rad, got {q.shape}")
        if not np.all(np.isfinite(q)):
            raise ValueError(f"q must be finite (rad), got {q}")
        if not np.array_equal(q, self._q):
            self.plant.SetPositions(self._context, q)
            self._q = q.copy()

    def pose(self, frame: str, q) -> tuple[np.ndarray, np.ndarray]:
        """(R_W<frame> (3, 3), p_W<frame> (3,) mm) of frame F, I, T, S or P at q."""
        self._set(q)
        X = self._frames[frame].CalcPoseInWorld(self._context)
        return X.rotation().matrix(), MM_PER_M * X.translation()

    def point(self, frame: str, p_frame_mm, q) -> np.ndarray:
        """Position (3,) mm in W of a point fixed in `frame` at p_frame_mm (3,) mm."""
        R, p = self.pose(frame, q)
        return p + R @ np.asarray(p_frame_mm, dtype=float)

    def jacobian(self, frame: str, p_frame_mm, q) -> np.ndarray:
        """(3, 6) translational Jacobian, mm/rad, of the point p_frame_mm fixed in `frame`, in W."""
        self._set(q)
        J = self.plant.CalcJacobianTranslationalVelocity(
            self._context, JacobianWrtVariable.kQDot, self._frames[frame],
            np.asarray(p_frame_mm, dtype=float) / MM_PER_M, self.plant.world_frame(), self.plant.world_frame(),
        )
        return MM_PER_M * J

    def shaft(self, q) -> tuple[np.ndarray, np.ndarray]:
        """(p_WI (3,) mm: a point on the shaft axis, u_W (3,): unit direction towards the tip)."""
        R, p = self.pose("I", q)
        return p, R[:, 0]

    def rcm_error_mm(self, q, p_WC) -> float:
        """Distance (mm) of the trocar point p_WC from the shaft line at q."""
        p, u = self.shaft(q)
        d = np.asarray(p_WC, dtype=float) - p
        return float(np.linalg.norm(d - (d @ u) * u))

    def rcm_rows(self, q, p_WC, gain_per_s: float = 50.0) -> tuple[np.ndarray, np.ndarray]:
        """RCM equality rows (A (2, 6), b (2,)) for qdot in rad/s: the material shaft point at
        the trocar may move only along the shaft, and its lateral error e (mm) decays as
        de/dt = -gain e (drift correction)."""
        p, u = self.shaft(q)
        lam = float(u @ (np.asarray(p_WC, dtype=float) - p))  # shaft coordinate of the trocar, mm
        p_WQ = p + lam * u
        J = self.jacobian("I", [lam, 0.0, 0.0], q)
        helper = np.array([0.0, 0.0, 1.0]) if abs(u[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
        n1 = np.cross(u, helper)
        n1 /= np.linalg.norm(n1)
        n2 = np.cross(u, n1)
        N = np.vstack([n1, n2])
        return N @ J, -gain_per_s * (N @ (p_WQ - np.asarray(p_WC, dtype=float)))

    def joint_margin_rad(self, q) -> np.ndarray:
        """(6,) distance of each joint to its nearer limit, rad (negative: beyond it)."""
        q = np.asarray(q, dtype=float)
        return np.minimum(q - self.q_lower, self.q_upper - q)
