"""The ground-truth eyes (the retina), placeable at any pose: `make_eye(name, pose)` for
each of EYE_SHAPES, the Eye it returns, and the EyePose X_WE that places it in W.

Frame E (design.md): origin at the centre of the retinal ellipsoid, z = visual axis
pointing anterior, x horizontal (+x temporal), y vertical (+y superior). Units: mm, rad.
"""
from models.eyes.catalog import (
    EMMETROPIC_RADII_MM, EYE_PARAMS, EYE_SHAPES, RADII_PER_MYOPIC_DIOPTRE_MM, check_eye_params, detached_rho, make_eye,
    param_range, pointed_rho, radii_for_refraction, staphyloma_rho,
)
from models.eyes.eye import ANTERIOR_CROP_MM, ELLIPSOIDAL_RETINA, Eye, retina_hits
from models.eyes.pose import EyePose

__all__ = ["ANTERIOR_CROP_MM", "ELLIPSOIDAL_RETINA", "EMMETROPIC_RADII_MM", "EYE_PARAMS", "EYE_SHAPES", "RADII_PER_MYOPIC_DIOPTRE_MM", "Eye",
           "EyePose", "check_eye_params", "detached_rho", "make_eye", "param_range", "pointed_rho", "radii_for_refraction", "retina_hits", "staphyloma_rho"]
