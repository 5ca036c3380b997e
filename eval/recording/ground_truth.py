"""A fit against its printed phantom's STL: loading and checking the mesh, registering
the recording's points to it (models.shapes.icp), and the fitted model's error there.

The mesh (frame M, mm) is the phantom's lower half as `vitreoguard eyes --stl` writes
it, or any watertight mesh whose inner surface is the retina. The points are paired with
the retina's faces alone (those facing its centre within 60 deg: not the outer wall or
the rim). Registration needs no initial placement: the fitted model's centre goes onto
the mesh retina's centre (the same kind of fit to the faces that face it; a model whose
semi-axes are no eye's, as a pointed eye's scan can fit, gives way to a sphere fitted to
the points); of 4,000 uniformly random rotations about it, the 3 that bring 300 of the
points closest to the mesh start a point-to-plane ICP
with a 3 mm correspondence distance (30 iterations); the start with the smallest RMS
residual is turned about its least defined axis to the best angle (every 3 deg, then
0.25 deg: about a near-symmetry axis the cost is too flat for the ICP to follow) and run
again; the result is refined with `max_distance_mm` (the paper: 0.1-1.0 mm; `sweep`
refines from it with each of 0.1, 0.2, ..., 1.0 mm). With the points' beams, when their
distances come from the project's extractor (the default OctEngine), the extractor's bias
is then removed before a last refinement: each point moves back along its beam by the
bias the extractor's table gives (models.iioct.error_model on the grid BIAS_DISTANCES_MM
x BIAS_INCIDENCES_DEG, about 10 s to tabulate once per process) at its distance and its
incidence on the placed mesh (the face it lies on). The bias (0 at normal incidence, 4-9
um at 20-40 deg, more beyond 14 mm) is shared by the points and the model fitted to them;
left in, it moves the mesh with the points where the retina tilts against the beam, and
drops out of `mae_um`; removed from the registration's points alone, it stays in the
model, where `mae_um` measures it.

With the points' displacements under the sensor's lateral calibration error
(eval.recording.fit.sensor_displacements: an offset across the beam and a tilt of it, 4
parameters in the sensor frame), the refinements estimate that error with the placement
(models.shapes.icp.register_to_mesh's `displacements`; prior SD: the safety filter's
declared calibration bound, 0.03 mm and 0.13 deg), and the dict's "sensor_error" holds
it. The bench scan's two passes, the instrument turned by 180 deg about its shaft
between them, see it displace their points in opposite directions; they cancel it in
the sum of squares only where both passes put as many points, and the half turn itself
(1 s at the rim, the error turning with the instrument), the model's gate and the passes'
different sampling leave them unequal: on the hyperopic eye, whose tilts only its
asphericity defines, what they left tilted the placement 0.076 deg off (0.045 with the
true sensor pose). Estimated, the error leaves the points (recovered there to 0.3 um and
0.002 deg; the placement 0.032 deg off).

`mae_um`: the area-weighted mean, over the mesh's retina faces (those the points are
paired with) within 2 mm of the model, of each face centroid's exact distance to the
fitted model after registration: the closed loop's exact MAE, on the printed half;
`lf_mae_um` the same for the local-global model (eval.recording.fit, step 6).

A placement is found modulo the mesh's own symmetries (`mesh_symmetries`: an
axis-aligned ellipsoid's half is itself turned by 180 deg) and only as well as the
geometry and the points define it: `placement_error` splits the rotation error over the
registration's principal axes with their SDs (models.shapes.icp.rotation_covariance).

Units: mm (um where named), rad (deg where named).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from eval.recording.bag import RecordingError
from models import fit_ellipsoid, fit_sphere
from models.adaptive.model import eyes_radii
from models.shapes.icp import MeshIndex, Registration, mesh_index, point_to_plane, register_to_mesh
from safety.inputs import FilterConfig

N_ROTATIONS = 4000
N_SCORE_POINTS = 300
COARSE_DISTANCE_MM = 3.0
MAX_POINTS = 40000
EYE_SIZE_MM = (10.0, 80.0)  # the extent of an eye phantom in mm
SWEEP_MM = tuple(np.round(np.arange(0.1, 1.01, 0.1), 1))
# the prior of the sensor's lateral calibration error the registration estimates (offset
# along S's x, y in mm, rotation about them in rad): the filter's declared calibration bound
SENSOR_PRIOR_SD = (FilterConfig.calibration_bound_mm, FilterConfig.calibration_bound_mm,
                   np.radians(FilterConfig.calibration_bound_deg), np.radians(FilterConfig.calibration_bound_deg))
# The extractor's bias table for the registration: 200 A-scans per cell (the extracted
# distance's SD is 2-30 um below 45 deg of incidence: the bias to about 1 um), each cell's
# mean error over the errors within BIAS_WITHIN_MM (what the ICP's least squares sees at
# its default correspondence distance; the median differs by up to 4 um below 45 deg), on
# a grid finer than the closed loop's where the bias changes fastest (0 at normal
# incidence, 5-7 um from 15-20 deg on) over the distances a scan of the posterior eye meets
BIAS_SAMPLES = 200
BIAS_WITHIN_MM = 1.0
BIAS_DISTANCES_MM = (2.0, 4.0, 6.0, 8.0, 11.0, 14.0, 17.0, 20.0)
BIAS_INCIDENCES_DEG = (0.0, 2.5, 5.0, 7.5, 10.0, 12.5, 15.0, 17.5, 20.0, 22.5, 25.0, 30.0, 35.0, 40.0, 45.0, 50.0, 55.0)


def load_stl(path) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) mm, faces (F, 3)) of the STL at `path`, vertices merged;
    RecordingError when it is unreadable, not watertight, or not in mm."""
    import trimesh

    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"--ground-truth {p} {'is a folder, not an STL file' if p.is_dir() else 'does not exist'}")
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


def _retina(index: MeshIndex, shape) -> tuple[np.ndarray, MeshIndex]:
    """(the centre (3,) mm in M of the mesh's retina, the MeshIndex of the retina's faces):
    the faces that face the centre of a sphere fitted to them within 60 deg (from a sphere
    fitted to every face, twice: the inner surface of a shell, the curved surface of a
    solid half), and the centre of the fit of `shape`'s kind (ellipsoid or sphere) to
    them. The registration pairs points with the retina's faces alone: a start about a
    wall's thickness off would pair points with the outer wall, where the ICP stops."""
    c = fit_sphere(index.centroids).center
    inner = np.ones(len(index.centroids), dtype=bool)
    for _ in range(2):
        to_c = c - index.centroids
        facing = np.einsum("ij,ij->i", index.normals, to_c) > 0.5 * np.linalg.norm(to_c, axis=1)
        if facing.sum() < 10:
            break
        inner = facing
        c = fit_sphere(index.centroids[inner]).center
    if hasattr(shape, "radii") and inner.sum() >= 10:
        c = fit_ellipsoid(index.centroids[inner]).center
    return c, MeshIndex(index.centroids[inner], index.normals[inner], index.areas[inner], cKDTree(index.centroids[inner]))


def _start_shape(model, P: np.ndarray):
    """The shape whose centre starts the registration: the fitted `model` (Sphere or
    Ellipsoid) when its semi-axes are an eye's (models.adaptive.model.eyes_radii; a
    sphere's three are its radius), else a sphere fitted to the points P (N, 3) mm (a
    pointed eye's partial scan can fit a 177 mm cigar whose centre lies 160 mm from the
    retina's)."""
    radii = np.broadcast_to(np.atleast_1d(getattr(model, "radii", getattr(model, "radius", np.nan))), 3)
    return model if eyes_radii(*(float(r) for r in radii)) else fit_sphere(P)


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


def _retina_faces(retina: MeshIndex, R: np.ndarray, p: np.ndarray, model) -> tuple[np.ndarray, np.ndarray]:
    """(centroids in W (K, 3) mm, areas (K,) mm^2) of the retina's faces (`_retina`) within
    2 mm of `model` under X_MW = (R, p)."""
    C_W = (retina.centroids - p) @ R
    keep = np.abs(model.signed_distance(C_W)) < 2.0
    return C_W[keep], retina.areas[keep]


def _mae_um(C: np.ndarray, A: np.ndarray, model) -> float:
    """The area-weighted mean exact distance (um) of the face centroids C (K, 3) mm, areas
    A (K,) mm^2, to `model` (anything with signed_distance)."""
    return 1e3 * float(np.sum(A * np.abs(model.signed_distance(C))) / np.sum(A)) if len(A) else float("nan")


def _result(reg, index: MeshIndex, model, max_distance_mm: float, local=None) -> dict:
    C, A = _retina_faces(index, reg.R, reg.p, model)  # the global model's retina faces, for both models
    mae = _mae_um(C, A, model)
    R_WE, p_WE = reg.R.T, -reg.R.T @ reg.p
    return {"max_distance_mm": float(max_distance_mm), "mae_um": mae, "registration_rmse_um": 1e3 * reg.rmse_mm,
            "lf_mae_um": None if local is None else _mae_um(C, A, local),
            "n_pairs": reg.n_pairs, "iterations": reg.iterations, "converged": reg.converged,
            "R_WE": R_WE.tolist(), "p_WE_mm": p_WE.tolist(),
            "rotation_sd_deg": [_finite_or_none(v) for v in np.degrees(reg.rotation_sd_rad)],
            "rotation_axes_E": reg.rotation_axes.T.tolist(),
            "sensor_error": None if not len(reg.xi) else {"offset_S_mm": reg.xi[:2].tolist(),
                                                          "rotvec_S_deg": np.degrees(reg.xi[2:]).tolist()}}


def _finite_or_none(v: float):
    return float(v) if np.isfinite(v) else None


def _turn_cost(X: np.ndarray, c: np.ndarray, axis: np.ndarray, a: float, index: MeshIndex) -> tuple[float, np.ndarray]:
    """(the ICP's truncated mean square cost, mm^2, of the points X (N, 3) mm in M turned by
    `a` rad about `axis` through c, with the translation that best follows the turn; that
    translation (3,) mm)."""
    Y = (X - c) @ Rotation.from_rotvec(a * axis).as_matrix().T + c
    dist, k = index.tree.query(Y, distance_upper_bound=COARSE_DISTANCE_MM)  # far points: no search
    near = dist <= COARSE_DISTANCE_MM
    if near.sum() < 6:
        return np.inf, np.zeros(3)
    n = index.normals[k[near]]
    r = np.einsum("ij,ij->i", Y[near] - index.centroids[k[near]], n)
    t = -np.linalg.lstsq(n, r, rcond=None)[0]
    r = r + n @ t
    return (float(np.sum(r * r)) + COARSE_DISTANCE_MM ** 2 * float(np.sum(~near))) / len(Y), t


def _turned_about_weak_axis(P: np.ndarray, index: MeshIndex, reg: Registration, c: np.ndarray,
                            n_score: int = 12000) -> Registration:
    """`reg` turned about its least defined rotation axis through c (3,) mm in M (the mesh
    retina's centre, on a near-symmetry axis) by the angle that, with its best translation,
    brings the points P closest to the mesh (the ICP's truncated mean square cost): every
    3 deg on a subsample of n_score points, then every 0.25 deg within 3 deg of the best on
    all of them; then the coarse ICP again from there. About a near-symmetry axis the cost
    changes by a few per cent over tens of degrees, too little for the ICP's damped steps
    to follow from a start far off; this scan starts it in the right valley."""
    X_all = P @ reg.R.T + reg.p
    X = X_all[np.linspace(0, len(P) - 1, min(len(P), n_score)).astype(int)]
    axis = reg.rotation_axes[:, 2]
    coarse = [(*_turn_cost(X, c, axis, a, index), a) for a in np.radians(np.arange(-180.0, 180.0, 3.0))]
    a0 = min(coarse, key=lambda e: e[0])[2]
    fine = [(*_turn_cost(X_all, c, axis, a, index), a) for a in a0 + np.radians(np.arange(-3.0, 3.01, 0.25))]
    _, t, a = min(fine, key=lambda e: e[0])
    T = Rotation.from_rotvec(a * axis).as_matrix()
    turned = register_to_mesh(P, index, T @ reg.R, T @ (reg.p - c) + c + t, COARSE_DISTANCE_MM, max_iterations=30)
    return turned if turned.rmse_mm <= reg.rmse_mm else reg


def debiased(P: np.ndarray, beams, index: MeshIndex, R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(N, 3) mm in W: the points P (N, 3) moved back along their beams (origins, unit
    directions, (N, 3) each, W) by the extractor's tabulated bias at their distance and
    their incidence on the mesh of `index` placed by X_MW = (R, p) (module docstring)."""
    from models.iioct import OctEngine
    from models.iioct.error_model import extractor_error_model
    from models.shapes.rays import incidences_rad

    O, U = (np.asarray(b, dtype=float) for b in beams)
    d = np.einsum("ij,ij->i", P - O, U)
    _, k = index.tree.query(P @ R.T + p)
    N_W = np.ascontiguousarray(index.normals[k] @ R)
    table = extractor_error_model(OctEngine(), BIAS_SAMPLES, 0, BIAS_DISTANCES_MM, BIAS_INCIDENCES_DEG, BIAS_WITHIN_MM)
    bias = table.interpolate(d, incidences_rad(N_W, np.ascontiguousarray(U)))[:, 1]
    return O + (d - bias)[:, None] * U


def register_fit(points_W, model, vertices, faces, max_distance_mm: float = 1.0, sweep: bool = False,
                 local=None, beams=None, displacements=None) -> dict:
    """Register the recording's points (N, 3) mm in W to the mesh (frame M = the phantom's
    E) and measure `model` (the fitted Sphere or Ellipsoid in W) there (module docstring):
    {"mae_um", "lf_mae_um" (the same for `local`, the local-global model's LocalField in
    W, on the same faces; None without it), "registration_rmse_um", "R_WE", "p_WE_mm" (the
    registered placement), "rotation_sd_deg", "rotation_axes_E" (its principal SDs and
    axes, models.shapes.icp.rotation_covariance),
    ..., and with `sweep` "sweep": one such dict per correspondence distance}. `beams`
    (origins, unit directions (N, 3) each, W) of the points, whose distances the
    project's extractor gave: its bias removed before the last refinement (module
    docstring). `displacements` (N, 3, 4): how each point moves under the sensor's lateral
    calibration error (eval.recording.fit.sensor_displacements): the refinements estimate
    it with the placement ("sensor_error")."""
    P = np.asarray(points_W, dtype=float)
    keep = np.linspace(0, len(P) - 1, MAX_POINTS).astype(int) if len(P) > MAX_POINTS else np.arange(len(P))
    P = P[keep]
    beams = None if beams is None else tuple(np.asarray(b, dtype=float)[keep] for b in beams)
    sensor = {} if displacements is None else {"displacements": np.asarray(displacements, dtype=float)[keep],
                                               "prior_sd": SENSOR_PRIOR_SD}
    start_shape = _start_shape(model, P)
    c_M, index = _retina(mesh_index(vertices, faces), start_shape)
    best = None
    for R0 in _best_rotations(P, start_shape.center, index, c_M):
        try:
            reg = register_to_mesh(P, index, R0, c_M - R0 @ start_shape.center, COARSE_DISTANCE_MM, max_iterations=30)
        except ValueError:
            continue
        score = reg.rmse_mm if reg.n_pairs >= 0.5 * len(P) else np.inf
        if best is None or score < best[0]:
            best = (score, reg)
    if best is None or not np.isfinite(best[0]):
        raise RecordingError("--ground-truth: the recording's points do not match the mesh at any start (fewer than half "
                             f"lie within {COARSE_DISTANCE_MM:g} mm of it): is it the phantom of this recording, in mm?")
    start = _turned_about_weak_axis(P, index, best[1], c_M)
    if beams is not None or sensor:
        start = register_to_mesh(P, index, start.R, start.p, max_distance_mm, **sensor)
    if beams is not None:
        P = debiased(P, beams, index, start.R, start.p)
    refined = [register_to_mesh(P, index, start.R, start.p, d, xi0=start.xi if sensor else None, **sensor)
               for d in (max_distance_mm, *(SWEEP_MM if sweep else ()))]
    out = _result(refined[0], index, model, max_distance_mm, local)
    if sweep:
        out["sweep"] = [_result(reg, index, model, d, local) for reg, d in zip(refined[1:], SWEEP_MM)]
    return out


def register_recording(result, vertices, faces, max_distance_mm: float = 1.0, sweep: bool = False,
                       remove_bias: bool = True) -> dict:
    """register_fit of a recording's fit (eval.recording.fit.FitResult): the points its
    model accepted, its model and local-global model, and their beams when the project's
    extractor gave the distances and `remove_bias` (False: the points registered as
    extracted). The dict's "bias_removed" says which."""
    beams = result.accepted_beams if remove_bias and result.oct.extracted else None
    out = register_fit(result.accepted, result.model.shape, vertices, faces, max_distance_mm, sweep, result.local, beams,
                       result.accepted_displacements)
    return {**out, "bias_removed": beams is not None}


def placed_mae_um(vertices, faces, model, R_WE, p_WE, local=None) -> float:
    """`mae_um` of `model` (in W) on the mesh placed at the known X_WE (R_WE (3, 3),
    p_WE (3,) mm), without registration; with `local` (a LocalField in W) its `lf_mae_um`
    on the same faces instead."""
    R = np.asarray(R_WE, dtype=float).T
    reg = Registration(R, -R @ np.asarray(p_WE, dtype=float), 0.0, 0, 0, True)
    out = _result(reg, _retina(mesh_index(vertices, faces), model)[1], model, 0.0, local)
    return out["mae_um"] if local is None else out["lf_mae_um"]


SYMMETRY_TOL_MM = 2e-3  # a rotation maps a mesh onto itself when no vertex moves further from it (facets: 0.7 um)


def mesh_symmetries(vertices, faces) -> list[np.ndarray]:
    """The rotations (3, 3) about the mesh frame's z axis by 0, 90, 180 and 270 deg that map
    the mesh (vertices (V, 3) mm, faces) onto itself within SYMMETRY_TOL_MM: an eye's lower
    half (z <= 0 in E, centred on E's origin) keeps its rim on z = 0 only under these. An
    axis-aligned ellipsoid's half is the same mesh turned by 180 deg: a registration can
    only find its placement modulo that turn."""
    V = np.asarray(vertices, dtype=float)
    index = mesh_index(V, faces)
    out = []
    for k in range(4):
        c, s = np.round(np.cos(k * np.pi / 2)), np.round(np.sin(k * np.pi / 2))
        S = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        r, dist, _ = point_to_plane(index, V @ S.T)
        if np.max(np.abs(r)) <= SYMMETRY_TOL_MM and np.max(dist) <= index.tree.query(V)[0].max() + SYMMETRY_TOL_MM:
            out.append(S)
    return out


def placement_error(registered: dict, R_WE, p_WE, defined_deg: float = 0.05, symmetries=None) -> dict:
    """The error of a registered placement (register_fit's dict) against the true X_WE
    (R_WE (3, 3), p_WE (3,) mm), modulo the mesh's `symmetries` (rotations in E that map
    it onto itself, `mesh_symmetries`; None: the identity alone): {"position_error_um",
    "rotation_error_deg" (the whole rotation, against the nearest placement of the same
    mesh), "rotation_error_about_axes_deg" (its components about the registration's
    principal axes, `rotation_axes_E`, most to least defined), "rotation_sd_deg" (their
    SDs), "defined_axes" (how many: 3 x SD <= defined_deg), "rotation_error_defined_deg"
    (the rotation error with the components about the undefined axes left out: the error
    modulo the rotations the geometry and the points' residual do not pin to defined_deg),
    "symmetry_turn_deg" (the turn about E's z of the nearest equivalent placement)}."""
    R_reg = np.asarray(registered["R_WE"])
    options = []
    for S in ([np.eye(3)] if symmetries is None else symmetries):
        R_eq = np.asarray(R_WE) @ S  # the same mesh, turned onto itself: the same physical placement
        v = Rotation.from_matrix(R_reg @ R_eq.T).as_rotvec()
        options.append((np.linalg.norm(v), R_eq, v, S))
    _, R_eq, v_W, S = min(options, key=lambda o: o[0])
    v_E = R_eq.T @ v_W  # the error's rotation vector in E (= M)
    axes = np.asarray(registered["rotation_axes_E"])  # rows
    sd = np.array([np.inf if v is None else v for v in registered["rotation_sd_deg"]])
    about = np.degrees(axes @ v_E)
    defined = 3.0 * sd <= defined_deg
    return {"position_error_um": 1e3 * float(np.linalg.norm(np.asarray(registered["p_WE_mm"]) - np.asarray(p_WE))),
            "rotation_error_deg": float(np.degrees(np.linalg.norm(v_E))),
            "rotation_error_about_axes_deg": about.tolist(), "rotation_sd_deg": registered["rotation_sd_deg"],
            "defined_axes": int(defined.sum()),
            "rotation_error_defined_deg": float(np.linalg.norm(about[defined])),
            "symmetry_turn_deg": float(np.degrees(np.arctan2(S[1, 0], S[0, 0])))}
