"""Point-to-plane ICP onto a mesh: a known placement is recovered."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from models.eyes import make_eye
from models.eyes.mesh import lower_half_shell
from models.shapes.icp import mesh_index, register_to_mesh
from models.shapes.sampling import unit_sphere_grid


def _posterior_points(eye, rng, noise_mm, n_theta=260, n_phi=520):
    """Retina points within 45 deg of the posterior pole (a spiral scan's region, ~20,000
    points as a 6-revolution recording gives), with Gaussian noise along the radius."""
    U = unit_sphere_grid(n_theta, n_phi)
    U = U[U[:, 2] < -np.cos(np.radians(45.0))]
    P = eye.surface_points(U)
    return P + noise_mm * rng.standard_normal(len(P))[:, None] * U


@pytest.mark.parametrize("name, noise_mm", [("staphyloma", 0.02), ("emmetropic", 0.0)])
def test_a_known_placement_is_recovered_within_the_targets(name, noise_mm):
    # the target: 20 um and 0.05 deg, with the paper's 20 um distance noise on the
    # staphyloma. An ellipsoid's 45 deg cap leaves two modes nearly free: the rotation about
    # the visual axis (0.09 mm x/y asymmetry) and a roll about a point ~1.5 mm from the
    # centre (20 um of noise moves it ~20 um): there the noise-free points check the ICP
    # itself, down to the facets' 0.7 um
    rng = np.random.default_rng(1)
    eye = make_eye(name)
    mesh = lower_half_shell(eye, edge_mm=0.25)
    index = mesh_index(*mesh)
    R_WE = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    p_WE = np.array([120.0, 5.0, 80.0])
    P_W = _posterior_points(eye, rng, noise_mm) @ R_WE.T + p_WE
    # start 0.5 mm and 3 deg (about the eye's centre) off the truth
    dR = Rotation.from_rotvec(np.radians(3.0) * np.array([0.6, 0.0, 0.8])).as_matrix()
    R0, p0 = dR @ R_WE.T, dR @ (-R_WE.T @ p_WE) + np.array([0.3, -0.3, 0.3])
    reg = register_to_mesh(P_W, index, R0, p0, max_distance_mm=1.0)
    assert reg.converged
    rot_err = np.degrees(Rotation.from_matrix(reg.R @ R_WE).magnitude())
    pos_err = np.linalg.norm(-reg.R.T @ reg.p - p_WE)
    if noise_mm:
        assert pos_err < 0.020 and rot_err < 0.05
        assert reg.rmse_mm == pytest.approx(noise_mm, rel=0.2)  # the noise, nothing more
    else:
        assert pos_err < 0.005 and reg.rmse_mm < 0.002


def test_points_far_from_the_mesh_are_refused():
    index = mesh_index(*lower_half_shell(make_eye("emmetropic"), edge_mm=1.0))
    with pytest.raises(ValueError, match="max_distance_mm"):
        register_to_mesh(np.full((100, 3), 500.0), index)
