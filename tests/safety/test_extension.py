"""Adding a constraint is one new definition plus passing the object to the filter: a
plane the tip and the cutter port must stay behind, defined here and nowhere else, is
honoured by the Python API and by the compiled closed loop."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from safety import FilterInputs, PointKinematics, SafetyFilter
from safety.constraints.base import Constraint, as_params


@njit(cache=True)
def fill_plane(sp, P, J, start, stop, G, h, ids, m, id0):
    """sp = [unit normal n (3), offset d mm, gain 1/s]: n . p <= d for the group's points,
    as the barrier n . J qdot <= gain (d - n . p)."""
    for i in range(stop - start):
        r = start + i
        for j in range(J.shape[2]):
            G[m, j] = sp[0] * J[r, 0, j] + sp[1] * J[r, 1, j] + sp[2] * J[r, 2, j]
        h[m] = sp[4] * (sp[3] - (sp[0] * P[r, 0] + sp[1] * P[r, 1] + sp[2] * P[r, 2]))
        ids[m] = id0 + i
        m += 1
    return m


@dataclass(frozen=True, eq=False)
class PlaneLimit(Constraint):
    normal: np.ndarray
    offset_mm: float
    group: str
    gain_per_s: float = 20.0
    name: str = "plane"

    kind = "inequality"
    filler = staticmethod(fill_plane)

    def params(self) -> np.ndarray:
        return as_params(np.asarray(self.normal) / np.linalg.norm(self.normal), self.offset_mm, self.gain_per_s)

    def max_rows(self, group_size: int) -> int:
        return group_size


def test_the_python_api_honours_an_added_plane():
    # toy robot: joints are the tip's coordinates (J = I, mm/rad), well inside a 12 mm sphere
    from models import Sphere

    plane = PlaneLimit(np.array([1.0, 0.0, 0.0]), 1.0, "boundary")
    f = SafetyFilter(extra=(plane,))
    p = np.array([0.0, 0.0, 0.0])
    for k in range(2000):  # 2 s pushing along +x at 5 mm/s, towards the plane x = 1 mm
        x = FilterInputs(t_s=k * 1e-3, q=p, q_min=np.full(3, -50.0), q_max=np.full(3, 50.0), qdot_max=np.full(3, 100.0),
                         v_cmd_W=np.array([5.0, 0.0, 0.0]), J_tip=np.eye(3),
                         boundary_points=[PointKinematics("tip", p, np.eye(3))], model=Sphere(np.zeros(3), 12.0),
                         model_time_s=k * 1e-3, sensor_time_s=k * 1e-3)
        out = f(x)
        assert out.ok
        p = p + 1e-3 * out.qdot
    assert p[0] <= 1.0 + 1e-9 and p[0] > 0.99  # held at the plane, reached to within 1 %
    assert "plane:tip" in out.active


def test_the_compiled_loop_honours_an_added_plane():
    from eval.closed_loop import ClosedLoop, LoopConfig
    from planning import SurgeryScenario, start_posture

    scenario = SurgeryScenario()
    free = ClosedLoop(scenario)
    c, R = scenario.eye_pose.p_WE, scenario.eye_pose.R_WE
    p0 = c + R @ np.array([0.0, 0.0, -4.0])  # 4 mm behind the eye centre, on the visual axis
    q0 = start_posture(free.robot, p0, scenario.p_WC)
    n_W = R @ np.array([0.0, 0.0, -1.0])  # push posteriorly, towards a plane 1 mm further
    offset = float(n_W @ p0) + 1.0

    def push(t_s, p_WT, q):
        return 3.0 * n_W, 0.0

    fenced = ClosedLoop(scenario, LoopConfig(extra_constraints=(PlaneLimit(n_W, offset, "tip_port"),)))
    runs = {}
    for name, loop in (("free", free), ("fenced", fenced)):
        runs[name] = loop.run(push, q0, 1.0)
    depth = {name: np.array([n_W @ loop.robot.pose("T", q)[1] for q in r.q]) - offset
             for (name, r), loop in zip(runs.items(), (free, fenced))}
    # the prior alone lets the tip pass the plane (3 mm/s for ~1 s); the plane stops it there
    assert depth["free"].max() > 1.0
    assert runs["fenced"].ok.all() and depth["fenced"].max() <= 1e-3
    assert depth["fenced"].max() > -0.05  # it got there
