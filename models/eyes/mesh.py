"""Printable phantoms: an eye shape's lower (posterior, z <= 0 in E) half as a closed
triangle shell, as the paper 3-D printed its six shapes.

The shell's inner surface is the retina (`Eye.surface_points` on a latitude-longitude
grid of directions from the centre, the posterior pole its apex, the equator z = 0 its
rim); its outer surface lies `wall_mm` further out along the same directions (the shape
is star-shaped about its centre, so the two never cross); a flat annulus at z = 0 closes
the wall. Every edge joins exactly two faces with opposite directions and the normals
point out of the material (into the cavity on the retina): a watertight solid, in mm,
in the eye frame E (origin at the retina's centre).

With `edge_mm` 0.25 the facets deviate from the smooth retina by less than
edge^2 / (8 R) = 0.7 um (R >= 11 mm): far below the 20 um registration target.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from models.eyes.eye import Eye
from models.shapes.validation import as_positive


class TriangleMesh(NamedTuple):
    """Vertices (V, 3) mm and faces (F, 3) vertex indices, counter-clockwise seen from
    the side their normal points to."""

    vertices: np.ndarray
    faces: np.ndarray


def _hemisphere_grid(n_rings: int, n_around: int) -> np.ndarray:
    """(1 + n_rings n_around, 3) unit directions in E: the posterior pole (0, 0, -1), then
    rings at polar angles (from the pole) k / n_rings x 90 deg, k = 1..n_rings (the last
    ring on the equator z = 0), each with n_around directions counter-clockwise about +z."""
    theta = np.arange(1, n_rings + 1) * (0.5 * np.pi / n_rings)
    phi = np.arange(n_around) * (2.0 * np.pi / n_around)
    T, P = np.meshgrid(theta, phi, indexing="ij")
    D = np.column_stack([(np.sin(T) * np.cos(P)).ravel(), (np.sin(T) * np.sin(P)).ravel(), (-np.cos(T)).ravel()])
    D[-n_around:, 2] = 0.0  # the rim exactly on z = 0
    return np.vstack([[0.0, 0.0, -1.0], D])


def _cap_faces(n_rings: int, n_around: int, offset: int) -> np.ndarray:
    """Faces of the hemispherical grid (vertex indices + offset), normals towards the
    centre: the pole's fan, then two triangles per quad between consecutive rings."""
    j = np.arange(n_around)
    jn = (j + 1) % n_around
    fan = np.column_stack([np.zeros(n_around, dtype=int), 1 + j, 1 + jn])
    quads = []
    for i in range(n_rings - 1):
        a, b = 1 + i * n_around, 1 + (i + 1) * n_around
        quads.append(np.column_stack([a + j, b + j, b + jn]))
        quads.append(np.column_stack([a + j, b + jn, a + jn]))
    return np.vstack([fan, *quads]) + offset


def lower_half_shell(eye: Eye, wall_mm: float = 1.0, edge_mm: float = 0.25) -> TriangleMesh:
    """The printable lower half of `eye` (its shape in E; the eye's pose is ignored): a
    watertight shell whose inner surface is the retina for z <= 0 (mm, E), `wall_mm`
    thick, facets about `edge_mm` long (module docstring)."""
    wall = as_positive(wall_mm, "wall_mm")
    edge = as_positive(edge_mm, "edge_mm")
    if edge > 2.0:
        raise ValueError(f"edge_mm must be in (0, 2] mm, got {edge_mm}")
    r_max = float(np.max(eye.radii))
    n_rings = max(int(np.ceil(0.5 * np.pi * r_max / edge)), 4)
    n_around = max(int(np.ceil(2.0 * np.pi * r_max / edge)), 12)
    D = _hemisphere_grid(n_rings, n_around)
    inner = eye.pose.to_E(eye.surface_points(D))
    inner[-n_around:, 2] = 0.0
    outer = inner + wall * D
    n = len(D)
    inner_faces = _cap_faces(n_rings, n_around, 0)
    outer_faces = _cap_faces(n_rings, n_around, n)[:, ::-1]  # reversed: normals away from the centre
    j = np.arange(n_around)
    jn = (j + 1) % n_around
    a, b = n - n_around + j, 2 * n - n_around + j  # the rim rings of the inner and outer surfaces
    an, bn = n - n_around + jn, 2 * n - n_around + jn
    rim = np.vstack([np.column_stack([a, b, bn]), np.column_stack([a, bn, an])])  # normals +z
    return TriangleMesh(np.vstack([inner, outer]), np.vstack([inner_faces, outer_faces, rim]).astype(np.int64))
