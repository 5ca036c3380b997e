"""What we know about the eye, in plain NumPy/SciPy (no Drake): shapes, fits, the adaptive model.

Millimetres everywhere; points in whatever frame the caller uses (W or E).
"""
from models.adaptive import AdaptiveEyeModel, ModelUpdate
from models.ellipsoid import Ellipsoid
from models.ellipsoid_fit import EllipsoidFit, IncrementalEllipsoidFit, fit_ellipsoid
from models.sphere import Sphere, fit_sphere
from models.sphere_kalman import SphereKalmanFilter
from models.transition import PaperCriteria

__all__ = [
    "AdaptiveEyeModel",
    "Ellipsoid",
    "EllipsoidFit",
    "IncrementalEllipsoidFit",
    "ModelUpdate",
    "PaperCriteria",
    "Sphere",
    "SphereKalmanFilter",
    "fit_ellipsoid",
    "fit_sphere",
]
