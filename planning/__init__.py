"""The robot: Meca500 + instrument in Drake, the surgery scenario, RCM kinematics and scans.

Millimetres, seconds, radians at every public function; metres only inside Drake.
"""
import models.compiled_cache  # noqa: F401  (first: numba's cache folder, before any compiled function)
from planning.diffik import rcm_joint_velocity
from planning.ik import IKFailure, rcm_ik
from planning.robot import Robot
from planning.scan import ScanRun, plan_ik_scan, run_diffik, sample_ik_run, start_posture
from planning.scenario import SurgeryScenario

__all__ = [
    "IKFailure",
    "Robot",
    "ScanRun",
    "SurgeryScenario",
    "plan_ik_scan",
    "rcm_ik",
    "rcm_joint_velocity",
    "run_diffik",
    "sample_ik_run",
    "start_posture",
]
