"""What we know about the eye, in plain NumPy/SciPy/numba (no Drake): shapes, fits, the adaptive model.

Millimetres everywhere; points in whatever frame the caller uses (W or E).
"""
import models.compiled_cache  # noqa: F401, I001  (first: numba's cache folder, before any compiled function)
from models.adaptive.history import ModelUpdate
from models.adaptive.model import AdaptiveEyeModel
from models.adaptive.transition import PaperCriteria, PredictiveCriteria
from models.fit.ellipsoid_fit import EllipsoidFit, IncrementalEllipsoidFit, fit_ellipsoid
from models.fit.sphere_kalman import SphereKalmanFilter
from models.shapes.ellipsoid import Ellipsoid
from models.shapes.sphere import Sphere, fit_sphere

__all__ = [
    "AdaptiveEyeModel",
    "Ellipsoid",
    "EllipsoidFit",
    "IncrementalEllipsoidFit",
    "ModelUpdate",
    "PaperCriteria",
    "PredictiveCriteria",
    "Sphere",
    "SphereKalmanFilter",
    "fit_ellipsoid",
    "fit_sphere",
]
