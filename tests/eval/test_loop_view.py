"""Meshcat view of closed-loop runs: exact model and boundary meshes, and a recording with
the robot, the true retina, each model the filter used, the beam and the tip path."""
from __future__ import annotations

import numpy as np
import pytest
from pydrake.geometry import Meshcat
from scipy.spatial.transform import Rotation

from eval.closed_loop import ClosedLoop, ModelSnapshot
from eval.experiments.command_sources import VelocityReplayCommand
from eval.loop_view import direction_grid, eye_surface_mm, model_surface_mm, show_loop
from models import Ellipsoid, Sphere
from planning import SurgeryScenario, start_posture

ROUND_OFF_MM = 1e-9

SHAPES = [
    Sphere(np.array([1.0, -2.0, 3.0]), 11.5),
    Ellipsoid(np.array([300.0, 20.0, 150.0]), [12.0, 11.0, 10.0], Rotation.from_euler("xyz", [0.3, -0.2, 1.0]).as_matrix()),
]


@pytest.mark.parametrize("shape", SHAPES, ids=["sphere", "ellipsoid"])
@pytest.mark.parametrize("offset_mm", [0.0, 0.5, 1.55])
def test_model_meshes_lie_exactly_on_the_surface_or_its_inward_offset(shape, offset_mm):
    V, F = model_surface_mm(shape, offset_mm)
    # an inward offset smaller than the smallest radius of curvature (r_min^2 / r_max = 8.3 mm)
    np.testing.assert_allclose(shape.signed_distance(V), offset_mm, rtol=0, atol=ROUND_OFF_MM)
    assert F.min() == 0 and F.max() == len(V) - 1


def test_grid_triangles_face_outwards_and_close_the_surface():
    U, F = direction_grid(12, 24)
    A, B, C = U[F[:, 0]], U[F[:, 1]], U[F[:, 2]]
    n = np.cross(B - A, C - A)
    area = 0.5 * np.linalg.norm(n, axis=1)
    real = area > 1e-12  # triangles that touch a pole ring collapse to lines
    assert np.all(np.einsum("ij,ij->i", n[real], A[real] + B[real] + C[real]) > 0.0)
    # the faces tile the sphere: their total area approaches 4 pi from below (chords)
    assert 0.95 * 4.0 * np.pi < area.sum() < 4.0 * np.pi
    # every edge is shared by exactly two triangles (closed, no cracks), the pole rings'
    # coincident vertices aside
    E = np.sort(np.concatenate([F[real][:, [0, 1]], F[real][:, [1, 2]], F[real][:, [2, 0]]]), axis=1)
    E = E[(E.min(axis=1) >= 24) & (E.max(axis=1) < len(U) - 24)]
    _, counts = np.unique(E, axis=0, return_counts=True)
    assert len(counts) > 0 and np.all(counts == 2)


def test_bad_grid_is_refused():
    with pytest.raises(ValueError, match="n_theta"):
        direction_grid(2, 10)


@pytest.fixture(scope="module")
def runs():
    scenario = SurgeryScenario()
    loop = ClosedLoop(scenario)
    p_WT = scenario.eye_pose.to_W(np.array([[1.0, 1.0, -5.0]]))[0]  # 5 mm behind the eye centre
    run = loop.run(VelocityReplayCommand([0.0], [[2.0, 0.0, 0.0]]), start_posture(loop.robot, p_WT, scenario.p_WC), 0.1)
    return loop, [run, run]


def test_the_recording_shows_robot_retina_models_beam_and_path(runs):
    loop, rs = runs
    assert [e.kind for e in rs[0].model_epochs] == ["prior"]  # a fresh model: the prior bounds the motion
    meshcat = Meshcat()
    url = show_loop(loop.robot, rs, loop.config.margins, loop.config.filter.d_safe_mm, loop.prior,
                    eye=loop.scenario.eye, meshcat=meshcat, fps=50.0)
    assert url.startswith("http")
    for path in ("/drake/truth/retina", "/drake/model/0_0_prior/surface", "/drake/model/0_0_prior/boundary",
                 "/drake/model/1_0_prior/surface", "/drake/beam", "/drake/tip_path"):
        assert meshcat.HasPath(path), path
    V, _ = eye_surface_mm(loop.scenario.eye)
    np.testing.assert_allclose(loop.scenario.eye.signed_distance(V), 0.0, atol=1e-3)  # composite eyes: <= 1 um


def test_show_loop_refuses_empty_runs(runs):
    loop, rs = runs
    with pytest.raises(ValueError, match="at least one run"):
        show_loop(loop.robot, [], loop.config.margins, 0.5, loop.prior)


def test_a_model_epoch_starts_at_each_change_of_kind(runs):
    loop, _ = runs
    system = loop.model
    system.reset(system.model, system.coverage)
    kinds = ["prior", "prior", "sphere", "sphere", "ellipsoid", "ellipsoid"]
    for t, kind in enumerate(kinds):
        system._mark_epoch(ModelSnapshot(kind, None, float(t), np.nan, 0))
    assert [(e.kind, e.t_s) for e in system.epochs] == [("prior", 0.0), ("sphere", 2.0), ("ellipsoid", 4.0)]
