"""The ground-truth eye shapes by name: the retinal semi-axes for a refraction and the
composite shapes (pointed, staphyloma, detached) built on them, in the eye frame E
(models.eyes.pose). Units: mm, dioptres, deg where named."""
from __future__ import annotations

import numpy as np

from models.eyes.eye import Eye
from models.eyes.pose import EyePose
from models.eyes.radial import RadialFunction, bump_radial, ellipsoid_radial, paraboloid_backed_radial, sphere_union_radial

EYE_SHAPES = ("emmetropic", "myopic", "hyperopic", "pointed", "detached", "staphyloma")
# The shape parameters each composite shape takes: name -> (low, high, default); every range is
# (low, high] for lengths (a zero-size feature is the healthy eye) and [low, high] for angles.
# Lengths in mm, angles in deg (from the posterior pole: staphyloma temporal, detachment inferior).
EYE_PARAMS = {
    "pointed": {"apex_offset_mm": (0.0, 6.0, 2.0)},
    "staphyloma": {"depth_mm": (0.0, 4.0, 1.5), "curvature_radius_mm": (7.0, 12.0, 8.4), "blend_mm": (0.0, 3.0, 1.0),
                   "angle_deg": (0.0, 60.0, 15.0)},
    "detached": {"height_mm": (0.0, 5.0, 2.0), "base_diameter_mm": (2.0, 16.0, 10.0), "angle_deg": (0.0, 90.0, 40.0)},
}
EMMETROPIC_RADII_MM = np.array([11.455, 11.365, 10.148])  # Atchison 2005 (gkaModelEye)
# Full-dimension growth per dioptre of myopia: width +0.14, height +0.10, length +0.30 mm.
RADII_PER_MYOPIC_DIOPTRE_MM = np.array([0.07, 0.05, 0.15])


def radii_for_refraction(dioptres: float) -> np.ndarray:
    """Retinal semi-axes [x, y, z] mm for a refraction in dioptres (myopia < 0)."""
    return EMMETROPIC_RADII_MM - float(dioptres) * RADII_PER_MYOPIC_DIOPTRE_MM


def pointed_rho(radii: np.ndarray, apex_offset_mm: float = 2.0) -> RadialFunction:
    """Myopic anterior half (z >= 0) joined at the equator to a posterior paraboloid
    z = -h + h (x^2/a^2 + y^2/b^2), h = c + apex_offset: same rim, apex `apex_offset`
    behind the ellipsoid's posterior pole (a convex crease at the equator)."""
    return paraboloid_backed_radial(radii, float(radii[2]) + apex_offset_mm)


def staphyloma_rho(radii, centre_dir, depth_mm=1.5, curvature_radius_mm=8.4, blend_mm=1.0) -> RadialFunction:
    """The eye wall with a posterior outpouching: the union of the retinal ellipsoid and a
    sphere of radius `curvature_radius_mm` whose far wall lies `depth_mm` beyond the retina
    along `centre_dir`, joined by a C1 smooth maximum of width `blend_mm` (radial).
    With the defaults the walls meet at about 21 deg before blending."""
    u0 = centre_dir / np.linalg.norm(centre_dir)
    D = float(ellipsoid_radial(radii)(u0[None])[0]) + depth_mm - curvature_radius_mm
    try:
        return sphere_union_radial(radii, u0, D, curvature_radius_mm, blend_mm)
    except ValueError as exc:  # its checks, in this function's parameters
        raise ValueError(f"staphyloma depth_mm={depth_mm} and curvature_radius_mm={curvature_radius_mm} "
                         f"put the sphere's centre {D:.2f} mm from the eye's: {exc}") from exc


def detached_rho(radii, centre_dir, height_mm=2.0, base_diameter_mm=10.0) -> RadialFunction:
    """The eye wall with the retina lifted towards the centre by up to `height_mm` over a
    region of `base_diameter_mm` about `centre_dir`; profile (1 - t^2)^2 in the angle
    ratio t, smooth inside and C1 at the rim."""
    u0 = centre_dir / np.linalg.norm(centre_dir)
    alpha_b = 0.5 * base_diameter_mm / float(ellipsoid_radial(radii)(u0[None])[0])
    return bump_radial(radii, u0, alpha_b, height_mm)


def param_range(shape: str, name: str) -> str:
    """The allowed range of shape parameter `name` of `shape` as text, e.g. '(0, 4] mm'."""
    lo, hi, _ = EYE_PARAMS[shape][name]
    unit = "deg" if name.endswith("_deg") else "mm"
    return f"{'[' if unit == 'deg' else '('}{lo:g}, {hi:g}] {unit}"


def check_eye_params(shape: str, params: dict) -> dict:
    """`params` as floats after checking each name and value against EYE_PARAMS[shape];
    raises ValueError (one line naming the parameter and its range) otherwise."""
    known = EYE_PARAMS.get(shape, {})
    out = {}
    for name, value in params.items():
        if name not in known:
            takes = ", ".join(f"{k} {param_range(shape, k)}" for k in known) if known else "no shape parameters"
            raise ValueError(f"eye shape {shape!r} has no parameter {name!r}; it takes {takes}")
        lo, hi, _ = known[name]
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise ValueError(f"{shape} {name} must be a number in {param_range(shape, name)}, got {value!r}")
        v = float(value)
        inside = (lo <= v <= hi) if name.endswith("_deg") else (lo < v <= hi)
        if not (np.isfinite(v) and inside):
            raise ValueError(f"{shape} {name} must be in {param_range(shape, name)}, got {value}")
        out[name] = v
    return out


def make_eye(name: str = "emmetropic", pose: EyePose | None = None, **params) -> Eye:
    """Ground-truth eye `name` (one of EYE_SHAPES) placed at `pose` (default: E = W).

    Keyword parameters override the defaults of the composite shapes:
    pointed: apex_offset_mm; staphyloma: depth_mm, curvature_radius_mm, blend_mm,
    angle_deg (temporal of the posterior pole); detached: height_mm, base_diameter_mm,
    angle_deg (inferior of the posterior pole). Names and ranges: EYE_PARAMS; a name the
    shape does not take or a value outside its range raises ValueError.
    """
    if name not in EYE_SHAPES:
        raise ValueError(f"unknown eye shape {name!r}; expected one of {', '.join(EYE_SHAPES)}")
    if pose is not None and not isinstance(pose, EyePose):
        raise ValueError(f"pose must be a models.eyes.EyePose or None, got {type(pose).__name__}")
    pose = EyePose() if pose is None else pose
    params = check_eye_params(name, params)
    if name in ("emmetropic", "myopic", "hyperopic"):
        return Eye(name, radii_for_refraction({"emmetropic": 0.0, "myopic": -12.0, "hyperopic": 4.0}[name]), pose)
    radii = radii_for_refraction(-12.0)
    if name == "pointed":
        return Eye(name, radii, pose, pointed_rho(radii, **params))
    angle = np.radians(params.pop("angle_deg", 15.0 if name == "staphyloma" else 40.0))
    if name == "staphyloma":
        centre = np.array([np.sin(angle), 0.0, -np.cos(angle)])
        return Eye(name, radii, pose, staphyloma_rho(radii, centre, **params))
    centre = np.array([0.0, -np.sin(angle), -np.cos(angle)])
    return Eye(name, radii, pose, detached_rho(radii, centre, **params))
