"""Ground-truth eyes: dimensions from the design, exact/sub-um ray casting, physical
(star-shaped, continuous) composite surfaces, pose equivariance, paper sampling."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from models.eyes import EYE_SHAPES, EyePose, make_eye
from models.sampling import unit_sphere_grid

MYOPIC = np.array([12.295, 11.965, 11.948])


def _from_centre(eye, U_E):
    """Ray-cast distances from the eye centre along E directions U_E."""
    O = np.tile(eye.pose.p_WE, (len(U_E), 1))
    return eye.ray_cast(O, U_E @ eye.pose.R_WE.T)


@pytest.mark.parametrize(
    "name, radii",
    [("emmetropic", [11.455, 11.365, 10.148]), ("myopic", MYOPIC), ("hyperopic", [11.175, 11.165, 9.548])],
)
def test_regular_shapes_have_the_design_semi_axes(name, radii):
    eye = make_eye(name)
    np.testing.assert_allclose(_from_centre(eye, np.eye(3)), radii, atol=1e-12)


def test_pathologies_have_the_design_dimensions():
    pointed = make_eye("pointed")
    assert _from_centre(pointed, np.array([[0, 0, -1.0]]))[0] == pytest.approx(MYOPIC[2] + 2.0, abs=1e-6)
    U_front = unit_sphere_grid(20, 40, 1.0)
    U_front = U_front[U_front[:, 2] > 0]
    np.testing.assert_allclose(_from_centre(pointed, U_front), _from_centre(make_eye("myopic"), U_front), atol=1e-6)
    a = np.radians(15.0)
    staph = np.array([[np.sin(a), 0.0, -np.cos(a)]])
    depth = _from_centre(make_eye("staphyloma"), staph) - _from_centre(make_eye("myopic"), staph)
    assert depth[0] == pytest.approx(1.5, abs=1e-6)
    a = np.radians(40.0)
    det = np.array([[0.0, -np.sin(a), -np.cos(a)]])
    lift = _from_centre(make_eye("myopic"), det) - _from_centre(make_eye("detached"), det)
    assert lift[0] == pytest.approx(2.0, abs=1e-6)


@pytest.mark.parametrize("name", ["pointed", "staphyloma", "detached"])
def test_composite_surfaces_are_physical(name):
    """Star-shaped (each ray from the centre crosses once: no overhang) and continuous
    (no crack): neighbouring directions give radii within the slope bound."""
    eye = make_eye(name)
    U = unit_sphere_grid(90, 180)
    r = _from_centre(eye, U)
    np.testing.assert_allclose(r, eye._star.rho(U), atol=1e-6)  # the first crossing is the surface
    G = r.reshape(90, 180)
    # grid steps are <= 0.035 rad; with wall slopes |dr/dtheta| < 25 mm/rad a step changes r by < 0.9 mm
    assert np.abs(np.diff(G, axis=1)).max() < 0.9 and np.abs(np.diff(G, axis=0)).max() < 0.9


@pytest.mark.parametrize("name", EYE_SHAPES)
def test_ray_hits_lie_on_the_retina(name):
    eye = make_eye(name, EyePose.anatomical())
    rng = np.random.default_rng(1)
    O = eye.pose.to_W(rng.uniform(-5.0, 5.0, (200, 3)))  # inside every shape (semi-axes >= 9.5 mm)
    D = rng.normal(size=(200, 3))
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    t = eye.ray_cast(O, D)
    assert np.all(np.isfinite(t)) and np.all(t > 0)
    hits = O + t[:, None] * D
    tol = 1e-9 if eye.is_ellipsoid else 1e-3  # exact; <= 1 um for the composites
    assert np.abs(eye.signed_distance(hits)).max() <= tol
    # first hit from inside: the segment before the hit stays inside
    mid = O + 0.5 * t[:, None] * D
    assert np.all(eye.signed_distance(mid) > 0)


@pytest.mark.parametrize("name", EYE_SHAPES)
def test_signed_distance_is_pose_equivariant(name):
    R = Rotation.from_euler("xyz", [10, -20, 35], degrees=True).as_matrix()
    pose = EyePose(R, [200.0, -30.0, 150.0])
    base, moved = make_eye(name), make_eye(name, pose)
    Q = np.random.default_rng(2).normal(0, 6, (60, 3))
    np.testing.assert_allclose(moved.signed_distance(pose.to_W(Q)), base.signed_distance(Q), atol=2e-6)


def test_reference_samples_are_cropped_and_on_the_surface():
    eye = make_eye("hyperopic", EyePose.anatomical())
    S = eye.reference_samples(100, 120)
    assert S.shape == (12_000, 3)
    assert np.abs(eye.signed_distance(S)).max() < 1e-9
    assert eye.pose.to_E(S)[:, 2].max() <= eye.anterior_z_mm - 5.0 + 1e-9


def test_unknown_shape_and_parameters_are_refused():
    with pytest.raises(ValueError, match="unknown eye shape"):
        make_eye("round")
    with pytest.raises(ValueError, match="no shape parameters"):
        make_eye("myopic", depth_mm=2.0)
    with pytest.raises(ValueError, match="R_WE"):
        EyePose(np.eye(3) * 2.0)
