"""The printable lower halves: watertight shells whose inner surface is the retina."""
import numpy as np
import pytest
import trimesh

from models.eyes import EYE_SHAPES, make_eye
from models.eyes.mesh import lower_half_shell


@pytest.mark.parametrize("name", EYE_SHAPES)
def test_the_lower_half_is_a_closed_shell_on_the_retina(name):
    eye = make_eye(name)
    mesh = lower_half_shell(eye, wall_mm=1.0, edge_mm=0.5)
    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    assert tm.is_watertight and tm.is_winding_consistent
    assert tm.volume > 0  # normals point out of the material
    V = mesh.vertices
    n = len(V) // 2
    # the inner surface lies on the retina (exact radial points), the outer 1 mm beyond it
    assert np.abs(eye.signed_distance(V[:n])).max() < 1e-9
    assert np.all(eye.signed_distance(V[n:]) < -0.5)
    assert V[:, 2].max() <= 1e-12 and V[:, 2].min() < -9.0  # the posterior half, in mm
    # the shell's volume: the wall (1 mm) times the inner area, grown by the outer
    # surface's larger area (1 + w / r, r the mean radius), within 3 % (the radial wall
    # of an ellipsoid is a little thicker than its normal one)
    area = tm.area_faces[np.einsum("ij,ij->i", tm.face_normals, -tm.triangles_center) > 0.5 * np.linalg.norm(
        tm.triangles_center, axis=1)].sum()
    assert tm.volume == pytest.approx(area * 1.0 * (1.0 + 1.0 / eye.radii.mean()), rel=0.03)


def test_bad_mesh_parameters_are_refused():
    with pytest.raises(ValueError, match="edge_mm"):
        lower_half_shell(make_eye("emmetropic"), edge_mm=3.0)
    with pytest.raises(ValueError, match="wall_mm"):
        lower_half_shell(make_eye("emmetropic"), wall_mm=0.0)
