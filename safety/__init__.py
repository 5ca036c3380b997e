"""The virtual boundary: a QP safety filter on commanded joint velocities (mm, s, rad)."""
from safety.filter import FilterConfig, FilterInputs, FilterOutput, PointKinematics, SafetyFilter

__all__ = ["FilterConfig", "FilterInputs", "FilterOutput", "PointKinematics", "SafetyFilter"]
