"""The paper's accuracy metrics, in its sampled form and in our exact form.

- MAE: fitted model vs ground truth over the retina (anterior 5 mm cropped);
- MMAE: measured points vs ground truth (the measurement error);
- FMAE: measured points vs fitted model (the fit residual).
Each is a mean and SD of absolute distances, in mm.

Sampled form (the paper's, for comparability): both surfaces sampled 500 x 500, and
every distance taken to the nearest sample of the other surface; the discretisation
alone adds tens of um. Exact form (our targets): each ground-truth sample's exact
distance to the model surface, each measured point's exact distance to the truth or
the model.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from models.shapes.validation import as_points


@dataclass(frozen=True)
class MeanSD:
    """Mean and standard deviation of absolute distances, mm."""

    mean: float
    sd: float

    @classmethod
    def of(cls, distances: np.ndarray) -> MeanSD:
        a = np.abs(np.asarray(distances, dtype=float))
        if a.size == 0 or not np.all(np.isfinite(a)):
            raise ValueError("distances must be a non-empty array of finite values (mm)")
        return cls(float(a.mean()), float(a.std()))

    def as_list(self) -> list[float]:
        return [self.mean, self.sd]


def mae_exact(model, truth_samples) -> MeanSD:
    """MAE: exact |signed distance| of each ground-truth sample (M, 3) to the model, mm."""
    return MeanSD.of(model.signed_distance(as_points(truth_samples, "truth_samples")))


def mmae_exact(points, truth) -> MeanSD:
    """MMAE: exact distance of each measured point (N, 3) to the ground-truth retina, mm."""
    return MeanSD.of(truth.signed_distance(as_points(points, "points")))


def fmae_exact(points, model) -> MeanSD:
    """FMAE: exact distance of each measured point (N, 3) to the fitted model, mm."""
    return MeanSD.of(model.signed_distance(as_points(points, "points")))


def model_samples(model, truth, n_theta: int = 500, n_phi: int = 500) -> np.ndarray:
    """The paper's model sampling: n_theta x n_phi over the model surface, cropped to the
    truth's reference region (anterior 5 mm of the eye removed)."""
    S = model.sample_surface(n_theta, n_phi)
    return S[truth.in_reference_region(S)]


def nearest_sample_distance(points, samples) -> np.ndarray:
    """(N,) distance (mm) from each point to its nearest sample (the paper's cloud-to-cloud)."""
    return cKDTree(as_points(samples, "samples")).query(as_points(points, "points"))[0]


@dataclass(frozen=True)
class PaperMetrics:
    """MMAE, FMAE and MAE (mm) of one fitted model, both forms."""

    mmae: MeanSD
    fmae: MeanSD
    mae: MeanSD
    mmae_sampled: MeanSD
    fmae_sampled: MeanSD
    mae_sampled: MeanSD


def paper_metrics(model, truth, points, n_grid: int = 500, truth_samples=None) -> PaperMetrics:
    """All metrics of `model` (Sphere/Ellipsoid, frame W) fitted to measured `points`
    (N, 3) W against the ground-truth `truth` (models.eyes.Eye), with n_grid x n_grid
    sampling. Pass `truth_samples` to reuse a ground-truth sampling across models."""
    P = as_points(points, "points")
    T = truth.reference_samples(n_grid, n_grid) if truth_samples is None else truth_samples
    M = model_samples(model, truth, n_grid, n_grid)
    return PaperMetrics(
        mmae=mmae_exact(P, truth),
        fmae=fmae_exact(P, model),
        mae=mae_exact(model, T),
        mmae_sampled=MeanSD.of(nearest_sample_distance(P, T)),
        fmae_sampled=MeanSD.of(nearest_sample_distance(P, M)),
        mae_sampled=MeanSD.of(nearest_sample_distance(T, M)),
    )


@dataclass(frozen=True)
class SigmaHonesty:
    """How well a field's sigma covers its true error at samples of the true retina:
    `coverage` the fraction whose error is within 3 sigma (NaN without a finite sigma),
    `unsafe_fraction` the fraction where the model's retina lies beyond the true one (the
    field's signed distance there > 0: it overstates clearance) by more than 3 sigma, and
    `worst_excess_mm` the largest such excess (mm; <= 0 when 3 sigma holds on that side)."""

    coverage: float
    unsafe_fraction: float
    worst_excess_mm: float

    @classmethod
    def of(cls, signed_mm: np.ndarray, sigma_mm: np.ndarray) -> SigmaHonesty:
        """From the field's signed distances (mm, > 0 inside its retina) and sigmas (mm) at
        the true retina's samples."""
        signed, sigma = np.asarray(signed_mm, dtype=float), np.asarray(sigma_mm, dtype=float)
        if not np.isfinite(sigma).all():
            return cls(float("nan"), float("nan"), float("nan"))
        excess = signed - 3.0 * sigma
        return cls(float(np.mean(np.abs(signed) <= 3.0 * sigma)), float(np.mean(excess > 0.0)), float(excess.max()))


class WorstHonesty(NamedTuple):
    """The worst of SigmaHonesty figures measured at several points (`worst_honesty`)."""

    lowest_coverage: float
    lowest_at: float  # where (the caller's unit: a fraction of a scan, seconds)
    largest_unsafe_fraction: float
    largest_unsafe_at: float | None  # None when no sample was beyond 3 sigma on the unsafe side
    worst_excess_mm: float


def honesty_report(w: WorstHonesty | None, at_suffix: str) -> dict:
    """The figures of `w` as JSON keys: `lowest_sigma3_coverage`, `lowest_at<at_suffix>`,
    `largest_unsafe_fraction`, `largest_unsafe_at<at_suffix>`, `worst_excess_um`; each
    None when `w` is (nothing measured)."""
    keys = ("lowest_sigma3_coverage", f"lowest_at{at_suffix}", "largest_unsafe_fraction",
            f"largest_unsafe_at{at_suffix}", "worst_excess_um")
    if w is None:
        return dict.fromkeys(keys)
    return dict(zip(keys, (w.lowest_coverage, w.lowest_at, w.largest_unsafe_fraction, w.largest_unsafe_at,
                           1e3 * w.worst_excess_mm)))


def worst_honesty(at, coverage, unsafe_fraction, worst_excess_mm) -> WorstHonesty | None:
    """The worst of SigmaHonesty figures (arrays, one per point `at`; NaN where nothing was
    measured, left out): the lowest coverage and where (the first such point), the largest
    unsafe-side fraction and where, and the worst excess (mm). None when nothing was measured."""
    at, cov = np.asarray(at, dtype=float), np.asarray(coverage, dtype=float)
    unsafe, excess = np.asarray(unsafe_fraction, dtype=float), np.asarray(worst_excess_mm, dtype=float)
    if not np.isfinite(cov).any():
        return None
    k, j = int(np.nanargmin(cov)), int(np.nanargmax(unsafe))
    return WorstHonesty(float(cov[k]), float(at[k]), float(unsafe[j]), float(at[j]) if unsafe[j] > 0 else None,
                        float(np.nanmax(excess)))


def distances_and_sigmas(field, P) -> tuple[np.ndarray, np.ndarray]:
    """((M,) signed distance mm, (M,) uncertainty mm) of a distance field with `uncertainty`
    at P (M, 3) mm: one evaluation where the field answers all three queries in one call
    (models.shapes.field.KernelQueries' signed_distance_gradient_uncertainty, e.g.
    models.local.field.LocalField), else its two queries."""
    both = getattr(field, "signed_distance_gradient_uncertainty", None)
    if both is not None:
        h, _, u = both(P)
        return np.asarray(h, dtype=float), np.asarray(u, dtype=float)
    return np.asarray(field.signed_distance(P), dtype=float), np.asarray(field.uncertainty(P), dtype=float)


def sigma_honesty(field, samples) -> SigmaHonesty:
    """SigmaHonesty of a distance field with `uncertainty` (e.g. models.local.field.LocalField)
    at `samples` (N, 3) mm of the true retina (e.g. Eye.reference_samples), N >= 1."""
    samples = as_points(samples, "samples")
    if not len(samples):
        raise ValueError("sigma_honesty: samples must hold at least one point (N, 3) mm")
    return SigmaHonesty.of(*distances_and_sigmas(field, samples))


def field_report(field, truth, angle_from_data_rad, n_grid: int = 100, scanned_deg: float = 10.0) -> dict:
    """The accuracy and honesty of a model `field` (a distance field with `uncertainty`,
    e.g. models.local.field.LocalField, frame W) against the ground truth `truth`
    (models.eyes.Eye) over its n_grid x n_grid reference samples (the paper's region):
    mae_um (exact form: each sample's distance to the model's surface), scanned_p95_um
    (95th percentile over the samples within `scanned_deg` of a measured direction;
    `angle_from_data_rad(Q)` gives that angle, e.g. a CoverageView's), sigma3_coverage
    (fraction of the samples whose error is within 3 sigma; None for a field without a
    standard deviation, NaN uncertainty), scanned_fraction, sigma_um median and p95, and
    the side the barrier depends on (None without a standard deviation): the model's
    retina beyond the true one (the field's signed distance at the true retina's points
    > 0: it overstates clearance there) by more than 3 sigma, `sigma3_unsafe_fraction` of
    the samples, and `sigma3_worst_excess_um` the largest such excess (um; <= 0 when 3
    sigma holds on that side everywhere): a point held at d_safe + 3 sigma there comes
    that much inside d_safe."""
    T = truth.reference_samples(n_grid, n_grid)
    signed, sigma = distances_and_sigmas(field, T)
    err = np.abs(signed)
    scanned = np.asarray(angle_from_data_rad(T)) <= np.radians(scanned_deg)
    has_sigma = bool(np.isfinite(sigma).all())
    honesty = SigmaHonesty.of(signed, sigma)
    return {"sigma3_unsafe_fraction": honesty.unsafe_fraction if has_sigma else None,
            "sigma3_worst_excess_um": 1e3 * honesty.worst_excess_mm if has_sigma else None,
            "mae_um": 1e3 * float(err.mean()),
            "scanned_p95_um": 1e3 * float(np.percentile(err[scanned], 95)) if scanned.any() else float("nan"),
            "sigma3_coverage": honesty.coverage if has_sigma else None,
            "scanned_fraction": float(scanned.mean()),
            "sigma_um": ({"median": 1e3 * float(np.median(sigma)), "p95": 1e3 * float(np.percentile(sigma, 95))}
                         if np.isfinite(sigma).all() else None)}
