"""Rigid registration of measured points to a triangle mesh: point-to-plane ICP.

    reg = register_to_mesh(P_W, mesh, R0, p0, max_distance_mm=1.0)
    reg.R, reg.p            # X_MW: the points' frame W in the mesh's frame M (mm)

Correspondences: each point's nearest face centroid (scipy cKDTree over the centroids of
a fine mesh; pairs further apart than `max_distance_mm` are left out, Open3D's "maximum
correspondence distance"); residual: the signed distance to that face's plane. Each
iteration solves the linearised 6-parameter least squares (small rotation and
translation) with Levenberg-Marquardt damping: a step is taken only if it lowers the
truncated mean square residual (a point beyond the correspondence distance counts that
distance squared), else damped further. A near-spherical cap leaves rotations about its
centre weakly constrained, and undamped Gauss-Newton steps there overshoot by tens of
degrees. Steps compose exactly (scipy Rotation.from_rotvec); the ICP ends when the step
is below 1e-8 rad and 1e-8 mm or no damped step lowers the cost. On a 0.25 mm mesh the plane of the nearest centroid
stands for the surface within (0.125 mm)^2 / (2 x 11 mm) = 0.7 um.

What bounds the accuracy: the registered rotation about an axis is defined only as far as
rotating the mesh about it moves the surface against the points. An ellipsoid's cap
moves little under rotations about its centre (the regular eyes are near surfaces of
revolution: emmetropic semi-axes x, y 90 um apart, myopic y, z 17 um, hyperopic x, y
10 um), so there the points' noise and any systematic error in them (a sensor's
calibration, an extraction bias that grows with incidence) set the rotation, not the
ICP: `rotation_covariance` gives the SD the points' own residual leaves about each
principal axis (the Cramer-Rao bound). Measured on 20,000 points over the lower half (80
deg about the pole) with 12 um noise, from 3 deg and 0.5 mm off: 0.006 deg (staphyloma)
and 0.09 deg (detached), < 1.5 um, and about the near-symmetry axes 0.3 deg (emmetropic)
and 1 deg (myopic); plain Gauss-Newton from the truth ends within 0.02 deg of the same
places (myopic: 0.2 deg). eval.recording.ground_truth turns the start about the least
defined axis before this ICP, for that reason.

Why this and not a library's ICP (the same points, mesh and start):
- trimesh.registration.icp (MIT; it needs rtree for its closest points) is point-to-point
  and slides along the curved surface: after 200 iterations 0.8-2.6 deg and 2-28 um off,
  90-170 s per registration; this routine: 0.3-0.5 s;
- Open3D (the paper's) has point-to-plane ICP but its wheel is several hundred MB of
  rendering and GUI libraries (not measured here);
- this routine: 60 lines over SciPy, which the project has.

Points that share a systematic error with a known linear effect on each (a sensor's
calibration error: `displacements`, (N, 3, k) per unit of k parameters) can be registered
with it: the parameters join the 6 of the placement in the same least squares, with a
Gaussian prior, and their SDs are marginalised out of `rotation_covariance`.

Units: mm, rad.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from models.shapes.validation import as_points, as_positive


LAMBDA_START, LAMBDA_MIN, LAMBDA_MAX = 1e-3, 1e-9, 1e6  # damping relative to the mean curvature of the cost
STEP_TOL = 1e-8  # rad and mm: 10 nm at the eye's 11 mm radius


class MeshIndex(NamedTuple):
    """A mesh's face centroids (F, 3) mm, unit normals (F, 3), areas (F,) mm^2 and the
    k-d tree over the centroids."""

    centroids: np.ndarray
    normals: np.ndarray
    areas: np.ndarray
    tree: cKDTree


class Registration(NamedTuple):
    """X_MW = (R (3, 3), p (3,) mm): a point x of the measured frame W lies at R x + p in
    the mesh's frame M. `rmse_mm`: RMS point-to-plane residual of the final pairs;
    `n_pairs`: their number; `iterations`; `converged`; `rotation_sd_rad` (3,), ascending,
    and `rotation_axes` (3, 3), its columns the unit axes in M: the standard deviations of
    the registered rotation about its principal axes (`rotation_covariance`); `xi` (k,):
    the points' own displacement parameters estimated with it (register_to_mesh's
    `displacements`; empty without them)."""

    R: np.ndarray
    p: np.ndarray
    rmse_mm: float
    n_pairs: int
    iterations: int
    converged: bool
    rotation_sd_rad: np.ndarray = np.full(3, np.nan)
    rotation_axes: np.ndarray = np.eye(3)
    xi: np.ndarray = np.zeros(0)


def mesh_index(vertices, faces) -> MeshIndex:
    """The MeshIndex of a triangle mesh: vertices (V, 3) mm, faces (F, 3) indices
    (counter-clockwise about their normal); degenerate faces left out."""
    V = as_points(vertices, "vertices")
    F = np.asarray(faces, dtype=np.int64)
    A, B, C = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    N = np.cross(B - A, C - A)
    twice_area = np.linalg.norm(N, axis=1)
    keep = twice_area > 1e-12
    centroids = ((A + B + C) / 3.0)[keep]
    return MeshIndex(centroids, N[keep] / twice_area[keep, None], 0.5 * twice_area[keep], cKDTree(centroids))


def point_to_plane(index: MeshIndex, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(signed distance (N,) mm of each point X (N, 3) to the plane of its nearest face
    centroid, distance (N,) mm to that centroid, the face's index (N,))."""
    dist, k = index.tree.query(X)
    r = np.einsum("ij,ij->i", X - index.centroids[k], index.normals[k])
    return r, dist, k


def _cost(index: MeshIndex, P: np.ndarray, R: np.ndarray, p: np.ndarray, max_d: float):
    """(truncated mean square residual mm^2: a point further than max_d from its centroid
    counts max_d^2; the transformed points; their residuals, centroid distances, faces)."""
    X = P @ R.T + p
    r, dist, k = point_to_plane(index, X)
    pair = dist <= max_d
    return float(np.mean(np.where(pair, r * r, max_d * max_d))), X, r, pair, k


def rotation_covariance(X: np.ndarray, normals: np.ndarray, sigma_mm: float, extra=None,
                        extra_information=None) -> tuple[np.ndarray, np.ndarray]:
    """(sd (3,) rad ascending, axes (3, 3) unit columns in M): the principal standard
    deviations of a point-to-plane registration's rotation (about the points' centroid,
    the translation marginalised), for points X (N, 3) mm on planes with unit normals
    (N, 3) and independent residuals of SD sigma_mm: sigma^2 (J^T J)^-1, J the residuals'
    Jacobian (the Cramer-Rao bound of the least squares). `extra` (N, k): the residuals'
    derivatives with respect to k further parameters estimated with the placement
    (marginalised too), `extra_information` (k,) their prior's sigma_mm^2 / prior SD^2. A
    rotation about an axis the surface does not change under (a sphere's any axis, a
    surface of revolution's own axis) has an infinite SD: the geometry does not define it."""
    J = np.hstack([np.cross(X - X.mean(axis=0), normals), normals] + ([] if extra is None else [extra]))
    H = J.T @ J
    if extra_information is not None:
        H[6:, 6:] += np.diag(extra_information)
    # the rotation block of H^-1 = the inverse of H's Schur complement on the other parameters
    S = H[:3, :3] - H[:3, 3:] @ np.linalg.solve(H[3:, 3:], H[3:, :3])
    w, V = np.linalg.eigh(S)
    with np.errstate(divide="ignore"):
        sd = sigma_mm / np.sqrt(np.maximum(w, 0.0))
    order = np.argsort(sd)
    return sd[order], V[:, order]


def register_to_mesh(points, index: MeshIndex, R0=None, p0=None, max_distance_mm: float = 1.0,
                     max_iterations: int = 100, displacements=None, prior_sd=None, xi0=None) -> Registration:
    """Point-to-plane ICP of `points` (N, 3) mm onto the mesh of `index`, from the initial
    X_MW (R0, p0) (default identity); pairs further than `max_distance_mm` from their
    centroid are left out (module docstring). With `displacements` (N, 3, k) mm per unit
    in the points' frame, each point moves by displacements[i] @ xi, and the k parameters
    xi (from xi0, default 0) are estimated with the placement (a sensor's calibration error
    the points share), with a Gaussian prior of SD `prior_sd` (k,) against the residual's
    mean square at the start. Raises ValueError when fewer than 6 pairs remain (the points
    are nowhere near the mesh)."""
    P0 = as_points(points, "points")
    max_d = as_positive(max_distance_mm, "max_distance_mm")
    R = np.eye(3) if R0 is None else np.array(R0, dtype=float)
    p = np.zeros(3) if p0 is None else np.array(p0, dtype=float)
    A = np.zeros((len(P0), 3, 0)) if displacements is None else np.asarray(displacements, dtype=float)
    n_xi = A.shape[2]
    xi = np.zeros(n_xi) if xi0 is None else np.array(xi0, dtype=float)
    P = P0 + A @ xi
    cost, X, r, pair, k = _cost(index, P, R, p, max_d)
    # the prior as pseudo-residuals: sum r^2 + s^2 sum (xi / prior_sd)^2, s^2 the start's mean square
    s2 = cost
    info = s2 / np.asarray(prior_sd, dtype=float) ** 2 if n_xi else np.zeros(0)
    cost += float(np.sum(info * xi * xi)) / len(P)
    converged, it, lam = False, 0, None
    for it in range(1, max_iterations + 1):
        if pair.sum() < 6:
            raise ValueError(f"only {int(pair.sum())} of {len(P)} points lie within max_distance_mm = {max_d:g} mm "
                             "of the mesh: the initial placement is too far off, or the mesh is not of these points")
        n, x = index.normals[k[pair]], X[pair]
        E = np.einsum("ia,ab,ibk->ik", n, R, A[pair])  # d r / d xi
        J = np.hstack([np.cross(x, n), n, E])  # d r / d (rotation vector, translation, xi) at the identity step
        H, g = J.T @ J, J.T @ r[pair]
        H[6:, 6:] += np.diag(info)
        g[6:] += info * xi
        scale = np.trace(H[:6, :6]) / 6.0
        lam = LAMBDA_START if lam is None else lam
        while True:  # Levenberg-Marquardt: a step that lowers the cost, damped until it does
            step = np.linalg.solve(H + lam * scale * np.eye(6 + n_xi), -g)
            dR = Rotation.from_rotvec(step[:3]).as_matrix()
            R1, p1, xi1 = dR @ R, dR @ p + step[3:6], xi + step[6:]
            P1 = P0 + A @ xi1 if n_xi else P
            c1, *rest = _cost(index, P1, R1, p1, max_d)
            trial = (c1 + float(np.sum(info * xi1 * xi1)) / len(P), *rest)
            if trial[0] <= cost:
                lam = max(lam / 4.0, LAMBDA_MIN)
                break
            lam *= 8.0
            if lam > LAMBDA_MAX:  # no step lowers the cost: a minimum
                break
        if lam > LAMBDA_MAX:
            converged = True
            break
        R, p, xi, P = R1, p1, xi1, P1
        cost, X, r, pair, k = trial
        if np.linalg.norm(step[:3]) < STEP_TOL and np.linalg.norm(step[3:]) < STEP_TOL:
            converged = True
            break
    rmse = float(np.sqrt(np.mean(r[pair] ** 2))) if pair.any() else float("nan")
    if pair.sum() >= 6:
        n = index.normals[k[pair]]
        E = np.einsum("ia,ab,ibk->ik", n, R, A[pair]) if n_xi else None
        sd, axes = rotation_covariance(X[pair], n, rmse, E, info * rmse ** 2 / s2 if n_xi else None)
    else:
        sd, axes = np.full(3, np.nan), np.eye(3)
    return Registration(R, p, rmse, int(pair.sum()), it, converged, sd, axes, xi)
