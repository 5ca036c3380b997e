"""The virtual boundary: a QP safety filter on commanded joint velocities (mm, s, rad), built from constraint objects."""
import models.compiled_cache  # noqa: F401  (first: numba's cache folder, before any compiled function)
from safety.filter import SafetyFilter, default_constraints
from safety.inputs import FilterConfig, FilterInputs, FilterOutput, PointKinematics
from safety.stack import ConstraintStack

__all__ = ["ConstraintStack", "FilterConfig", "FilterInputs", "FilterOutput", "PointKinematics", "SafetyFilter",
           "default_constraints"]
