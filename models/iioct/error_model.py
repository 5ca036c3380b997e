"""The iiOCT extractor's error model: bias, SD and invalid probability of the extracted
distance as functions of the true distance (mm) and the incidence (rad), tabulated once per
process by running the full chain (models.iioct: synthesis and extraction), interpolated
bilinearly, and drawn from in compiled code (the 1 kHz closed loop's "distance" mode).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
from numba import njit

from models.iioct.ascan import OctEngine, synthesize_ascan
from models.iioct.segmentation import DistanceExtractor


@njit(cache=True)
def _grid_cell(grid, x):
    """(i, u): the cell [grid[i], grid[i + 1]] of x (clamped to the grid's first and last
    cells) and x's fraction u in [0, 1] across it (clamped)."""
    i = min(max(np.searchsorted(grid, x) - 1, 0), len(grid) - 2)
    return i, min(max((x - grid[i]) / (grid[i + 1] - grid[i]), 0.0), 1.0)


@njit(cache=True)
def _cell(D, A, d, a):
    """(i, j, u, v): the cell [D[i], D[i + 1]] x [A[j], A[j + 1]] of the grid D x A that
    holds (d, a) and the fractions u, v across it (both clamped as in `_grid_cell`)."""
    i, u = _grid_cell(D, d)
    j, v = _grid_cell(A, a)
    return i, j, u, v


@njit(cache=True)
def _bilinear_at(tables, cell, k):
    """Table k of `tables` (len(D), len(A), K) interpolated bilinearly in `cell` (`_cell`)."""
    i, j, u, v = cell
    return ((1 - u) * (1 - v) * tables[i, j, k] + u * (1 - v) * tables[i + 1, j, k]
            + (1 - u) * v * tables[i, j + 1, k] + u * v * tables[i + 1, j + 1, k])


@njit(cache=True)
def bilinear(D, A, tables, d, a):
    """(M, K) the K tables (len(D), len(A), K) interpolated bilinearly at the M points
    (d[m], a[m]), clamped at the grid's edges."""
    out = np.empty((len(d), tables.shape[2]))
    for m in range(len(d)):
        cell = _cell(D, A, d[m], a[m])
        for k in range(tables.shape[2]):
            out[m, k] = _bilinear_at(tables, cell, k)
    return out


@njit(cache=True)
def draw_one(D, A, tables, d, a, uniform, normal):
    """(extracted distance mm, NaN when invalid; valid) of one sample at the true distance
    d mm and incidence a rad from its draws `uniform` in [0, 1) and `normal` (standard):
    invalid where uniform < p_invalid, else d + bias + sd normal (tables as in
    `bilinear`: p_invalid, bias mm, sd mm)."""
    cell = _cell(D, A, d, a)
    if uniform < _bilinear_at(tables, cell, 0):
        return np.nan, False
    return d + _bilinear_at(tables, cell, 1) + _bilinear_at(tables, cell, 2) * normal, True


@njit(cache=True)
def _draw(D, A, tables, d, a, uniform, normal):
    """((M,) extracted distances mm, NaN where invalid; (M,) valid): `draw_one` of the M
    samples (true distances d mm, incidences a rad, draws uniform and normal (M,))."""
    out, valid = np.empty(len(d)), np.empty(len(d), dtype=np.bool_)
    for m in range(len(d)):
        out[m], valid[m] = draw_one(D, A, tables, d[m], a[m], uniform[m], normal[m])
    return out, valid


@dataclass(frozen=True)
class ExtractorErrorModel:
    """The extractor's error (extracted - true, mm) as a function of the true distance
    (mm) and the incidence (rad): `bias`, `sd` and `p_invalid` on the grid
    `distances_mm` x `incidences_rad`, interpolated bilinearly (clamped at the grid's
    edges). Errors are drawn Gaussian with that bias and SD."""

    distances_mm: tuple
    incidences_rad: tuple
    bias: list
    sd: list
    p_invalid: list

    @cached_property
    def grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(D (n,) mm, A (k,) rad, tables (n, k, 3): p_invalid, bias mm, sd mm): the
        compiled kernels' arguments (`bilinear`, `draw_one`)."""
        return (np.array(self.distances_mm), np.array(self.incidences_rad),
                np.ascontiguousarray(np.stack([self.p_invalid, self.bias, self.sd], axis=-1), dtype=float))

    def interpolate(self, distances_mm: np.ndarray, incidences_rad: np.ndarray) -> np.ndarray:
        """(M, 3) [p_invalid, bias mm, sd mm] at M true distances (mm) and incidences (rad)
        (finite, M >= 0)."""
        D, A, tables = self.grid
        return bilinear(D, A, tables, np.ascontiguousarray(distances_mm, dtype=float),
                        np.ascontiguousarray(incidences_rad, dtype=float))

    def draws(self, distances_mm: np.ndarray, incidences_rad: np.ndarray,
              rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """((M,) extracted distances mm, NaN where invalid; (M,) valid) for M true distances
        (mm) and incidences (rad): one uniform (invalid with probability p_invalid) and one
        standard normal per sample, drawn in two batches from `rng`."""
        D, A, tables = self.grid
        d, a = np.ascontiguousarray(distances_mm, dtype=float), np.ascontiguousarray(incidences_rad, dtype=float)
        return _draw(D, A, tables, d, a, rng.random(len(d)), rng.standard_normal(len(d)))


DISTANCES_MM = (0.5, 1.0, 2.0, 4.0, 8.0, 14.0, 20.0, 25.0)
INCIDENCES_DEG = (0.0, 20.0, 40.0, 55.0, 65.0, 75.0)


@lru_cache(maxsize=4)
def extractor_error_model(engine: OctEngine = OctEngine(), samples: int = 24, seed: int = 0,
                          distances_mm: tuple = DISTANCES_MM, incidences_deg: tuple = INCIDENCES_DEG,
                          mean_within_mm: float | None = None) -> ExtractorErrorModel:
    """Tabulate the extractor's bias, SD (robust: 1.4826 x MAD) and invalid fraction over
    the grid `distances_mm` x `incidences_deg` (default 0.5-25 mm, 0-75 deg) with `samples`
    A-scans per cell (about 1 s with the defaults; cached per process). The bias is the
    errors' median, or with `mean_within_mm` their mean over those within that many mm
    (what a least-squares fit that drops pairs beyond it sees)."""
    rng = np.random.default_rng(seed)
    extractor = DistanceExtractor(engine)
    D = np.array(distances_mm, dtype=float)
    A = np.radians(np.array(incidences_deg, dtype=float))
    bias, sd, p_invalid = (np.zeros((len(D), len(A))) for _ in range(3))
    for i, d in enumerate(D):
        for j, a in enumerate(A):
            m = [extractor(synthesize_ascan(d, a, rng, engine=engine)) for _ in range(samples)]
            err = np.array([x.distance_mm - d for x in m if x.valid])
            p_invalid[i, j] = 1.0 - len(err) / samples
            if len(err):
                med = float(np.median(err))
                bias[i, j], sd[i, j] = med, 1.4826 * float(np.median(np.abs(err - med)))
                near = err[np.abs(err) <= mean_within_mm] if mean_within_mm is not None else err[:0]
                if len(near):
                    bias[i, j] = float(near.mean())
    return ExtractorErrorModel(tuple(D), tuple(A), bias.tolist(), sd.tolist(), p_invalid.tolist())
