"""A fit against its printed phantom's STL: loading and checking the mesh, registering
the recording's points to it (models.shapes.icp), and the fitted model's error there.

The mesh (frame M, mm) is the phantom's lower half as `vitreoguard eyes --stl` writes
it, or any watertight mesh whose inner surface is the retina. Registration needs no
initial placement: the fitted model's centre goes onto the mesh retina's centre (the
same kind of fit to the faces that face it); of 4,000 uniformly random rotations about
it, the 3 that bring 300 of the points closest to the mesh start a point-to-plane ICP
with a 3 mm correspondence distance (30 iterations); the start with the smallest RMS
residual is refined with `max_distance_mm` (the paper: 0.1-1.0 mm; `sweep` refines from
it with each of 0.1, 0.2, ..., 1.0 mm).

`mae_um`: the area-weighted mean, over the mesh's retina faces (facing the model's centre
within 60 deg, within 2 mm of the model), of each face centroid's exact distance to the
fitted model after registration: the closed loop's exact MAE, on the printed half.

Units: mm (um where named), rad (deg where named).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from eval.recording.bag import RecordingError
from models import fit_ellipsoid, fit_sphere
from models.shapes.icp import MeshIndex, Registration, mesh_index, register_to_mesh

N_ROTATIONS = 4000
N_SCORE_POINTS = 300
COARSE_DISTANCE_MM = 3.0
MAX_POINTS = 40000
EYE_SIZE_MM = (10.0, 80.0)  # the extent of an eye phantom in mm
SWEEP_MM = tuple(np.round(np.arange(0.1, 1.01, 0.1), 1))


def load_stl(path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) mm, faces (F, 3)) of the STL at `path`, vertices merged;
    RecordingError when it is unreadable, not watertight, or not in mm."""
    import trimesh

    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"--ground-truth {p} does not exist")
    try:
        mesh = trimesh.load_mesh(p, file_type="stl")
    except Exception as exc:  # trimesh raises several types for a file that is no STL
        raise RecordingError(f"--ground-truth {p} is not a readable STL ({type(exc).__name__}: {exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise RecordingError(f"--ground-truth {p} holds no triangle mesh")
    if not mesh.is_watertight:
        raise RecordingError(f"--ground-truth {p} is not watertight (some edges do not join exactly two faces): "
                             "repair the mesh or export it closed")
    extent = float(np.max(mesh.extents))
    if not (EYE_SIZE_MM[0] <= extent <= EYE_SIZE_MM[1]):
        hint = " (metres?)" if extent < 1.0 else " (um?)" if extent > 1e3 else ""
        raise RecordingError(f"--ground-truth {p} spans {extent:g} units; an eye phantom in mm spans "
                             f"{EYE_SIZE_MM[0]:g}-{EYE_SIZE_MM[1]:g}{hint}")
    return np.asarray(mesh.vertices, dtype=float), np.asarray(mesh.faces, dtype=np.int64)


def _mesh_centre(index: MeshIndex, model) -> np.ndarray:
    """The centre (mm, M) of the mesh's retina: the fit of the model's kind (ellipsoid or
    sphere) to the centroids of the faces that face the centre of a first sphere fit
    (the inner surface of a shell, the curved surface of a solid half)."""
    c = fit_sphere(index.centroids).center
    for _ in range(2):
        to_c = c - index.centroids
        inner = np.einsum("ij,ij->i", index.normals, to_c) > 0.5 * np.linalg.norm(to_c, axis=1)
        if inner.sum() < 10:
            break
        C = index.centroids[inner]
        c = fit_ellipsoid(C).center if hasattr(model, "radii") else fit_sphere(C).center
    return c


def _best_rotations(P: np.ndarray, c_W: np.ndarray, index: MeshIndex, c_M: np.ndarray, k: int = 3) -> list[np.ndarray]:
    """The k of N_ROTATIONS rotations (uniform random, seeded) about the centres c_W -> c_M
    that bring a subsample of the points P (N, 3) mm closest to the mesh (mean distance
    to the nearest face centroid, clipped at COARSE_DISTANCE_MM)."""
    X = P[np.linspace(0, len(P) - 1, min(len(P), N_SCORE_POINTS)).astype(int)] - c_W
    Rs = Rotation.random(N_ROTATIONS, random_state=0).as_matrix()
    Y = np.einsum("rij,nj->rni", Rs, X) + c_M
    dist, _ = index.tree.query(Y.reshape(-1, 3), distance_upper_bound=COARSE_DISTANCE_MM)
    score = np.minimum(dist, COARSE_DISTANCE_MM).reshape(len(Rs), -1).mean(axis=1)
    return [Rs[i] for i in np.argsort(score)[:k]]


def _retina_faces(index: MeshIndex, R: np.ndarray, p: np.ndarray, model) -> tuple[np.ndarray, np.ndarray]:
    """(centroids in W (K, 3) mm, areas (K,) mm^2) of the mesh's retina faces (module
    docstring) under X_MW = (R, p)."""
    C_W = (index.centroids - p) @ R
    N_W = index.normals @ R
    to_centre = model.center - C_W
    cos = np.einsum("ij,ij->i", N_W, to_centre) / np.linalg.norm(to_centre, axis=1)
    keep = (cos > 0.5) & (np.abs(model.signed_distance(C_W)) < 2.0)
    return C_W[keep], index.areas[keep]


def _result(reg, index: MeshIndex, model, max_distance_mm: float) -> dict:
    C, A = _retina_faces(index, reg.R, reg.p, model)
    mae = float(np.sum(A * np.abs(model.signed_distance(C))) / np.sum(A)) if len(A) else float("nan")
    R_WE, p_WE = reg.R.T, -reg.R.T @ reg.p
    return {"max_distance_mm": float(max_distance_mm), "mae_um": 1e3 * mae, "registration_rmse_um": 1e3 * reg.rmse_mm,
            "n_pairs": reg.n_pairs, "iterations": reg.iterations, "converged": reg.converged,
            "R_WE": R_WE.tolist(), "p_WE_mm": p_WE.tolist()}


def register_fit(points_W, model, vertices, faces, max_distance_mm: float = 1.0, sweep: bool = False) -> dict:
    """Register the recording's points (N, 3) mm in W to the mesh (frame M = the phantom's
    E) and measure `model` (the fitted Sphere or Ellipsoid in W) there (module docstring):
    {"mae_um", "registration_rmse_um", "R_WE", "p_WE_mm" (the registered placement),
    ..., and with `sweep` "sweep": one such dict per correspondence distance}."""
    P = np.asarray(points_W, dtype=float)
    if len(P) > MAX_POINTS:
        P = P[np.linspace(0, len(P) - 1, MAX_POINTS).astype(int)]
    index = mesh_index(vertices, faces)
    c_M = _mesh_centre(index, model)
    best = None
    for R0 in _best_rotations(P, model.center, index, c_M):
        try:
            reg = register_to_mesh(P, index, R0, c_M - R0 @ model.center, COARSE_DISTANCE_MM, max_iterations=30)
        except ValueError:
            continue
        score = reg.rmse_mm if reg.n_pairs >= 0.5 * len(P) else np.inf
        if best is None or score < best[0]:
            best = (score, reg)
    if best is None or not np.isfinite(best[0]):
        raise RecordingError("--ground-truth: the recording's points do not match the mesh at any start (fewer than half "
                             f"lie within {COARSE_DISTANCE_MM:g} mm of it): is it the phantom of this recording, in mm?")
    start = best[1]
    out = _result(register_to_mesh(P, index, start.R, start.p, max_distance_mm), index, model, max_distance_mm)
    if sweep:
        out["sweep"] = [_result(register_to_mesh(P, index, start.R, start.p, d), index, model, d) for d in SWEEP_MM]
    return out


def placed_mae_um(vertices, faces, model, R_WE, p_WE) -> float:
    """`mae_um` of `model` (in W) on the mesh placed at the known X_WE (R_WE (3, 3),
    p_WE (3,) mm), without registration."""
    R = np.asarray(R_WE, dtype=float).T
    reg = Registration(R, -R @ np.asarray(p_WE, dtype=float), 0.0, 0, 0, True)
    return _result(reg, mesh_index(vertices, faces), model, 0.0)["mae_um"]


def placement_error(registered: dict, R_WE, p_WE) -> dict:
    """{"position_error_um", "rotation_error_deg"} of a registered placement against the
    true X_WE (R_WE (3, 3), p_WE (3,) mm)."""
    R = np.asarray(registered["R_WE"]) @ np.asarray(R_WE).T
    return {"position_error_um": 1e3 * float(np.linalg.norm(np.asarray(registered["p_WE_mm"]) - np.asarray(p_WE))),
            "rotation_error_deg": float(np.degrees(Rotation.from_matrix(R).magnitude()))}
