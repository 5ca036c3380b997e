"""What the closed loop's model knows of the retina: its figures against the ground truth
(models.metrics.field_report) and a map of its error and standard deviation.

The model reported is the one the filter used at the end of the spiral: with the local
model its LocalField (kind "local", or the global quadric's kind while the local
correction is not used), else the quadric the filter trusts (its uncertainty: 0 mm).
Units: mm in, um out; directions seen from the nominal eye centre.
"""
from __future__ import annotations

import numpy as np

from models.metrics import field_report, honesty_report, sigma_honesty, worst_honesty


class _ExactField:
    """A quadric shape as a field with no uncertainty (the quadric model's report)."""

    def __init__(self, shape):
        self.shape = shape

    def signed_distance(self, P):
        return self.shape.signed_distance(P)

    def uncertainty(self, P):
        return np.full(len(P), np.nan)  # the quadric boundary's margins are not a standard deviation


class BuildHonesty:
    """The local model's sigma against the true retina on the way through a build: called
    with each snapshot the filter reads (eval.systems.model.AdaptiveModelSystem.on_snapshot),
    it measures the snapshot's field every `every_s` s of simulated time over the eye's
    n_grid x n_grid reference samples (models.metrics.sigma_honesty). A snapshot without a
    field (the prior, the quadric model) is not measured. `summary()`: the worst of them."""

    def __init__(self, eye, every_s: float = 0.25, n_grid: int = 60):
        self.truth = eye.reference_samples(n_grid, n_grid)
        self.every_s = float(every_s)
        self._next_t = -np.inf
        self.rows: list[tuple] = []  # (t_s, SigmaHonesty)

    def __call__(self, snap) -> None:
        if snap.field is None or snap.t_s < self._next_t:
            return
        self._next_t = snap.t_s + self.every_s
        self.rows.append((snap.t_s, sigma_honesty(snap.field, self.truth)))

    def summary(self) -> dict | None:
        """`probes`; `lowest_sigma3_coverage` and when (`lowest_at_s`, s into the scan);
        `largest_unsafe_fraction` (beyond 3 sigma with the model's retina beyond the true
        one) and when (`largest_unsafe_at_s`, None if none); `worst_excess_um` (the largest
        such excess; <= 0 when 3 sigma held on that side at every probe). None without a
        probe."""
        w = worst_honesty([r[0] for r in self.rows], [r[1].coverage for r in self.rows],
                          [r[1].unsafe_fraction for r in self.rows], [r[1].worst_excess_mm for r in self.rows])
        if w is None:
            return None
        return {"probes": len(self.rows), **honesty_report(w, "_s")}


def filter_model(loop, build):
    """(kind, field) of the model the filter reads at the end of the spiral `build`
    (eval.experiments.boundary.SpiralBuild); field None for the prior."""
    snap = loop.model.snapshot_for(build.model, build.coverage, float(build.run.t[-1]))
    if snap.field is not None:
        return snap.kind, snap.field
    return snap.kind, None if snap.shape is None else _ExactField(snap.shape)


def model_summary(loop, build, n_grid: int = 100) -> dict:
    """boundary.json's, sensor.json's and plan.json's `model` figures of the filter's
    model: kind, mae_um, scanned_p95_um, sigma3_coverage (field_report), the local
    model's sigma calibration (LocalField.sigma_calibration; None for the quadric), its
    sigma on the way through the build (`on_the_way`: BuildHonesty.summary), and
    the scan's sensor samples and the valid ones the model did not take for their
    incidence on the filter's model (eval.systems.model.AdaptiveModelSystem)."""
    kind, field = filter_model(loop, build)
    out = {"kind": kind, "samples": build.samples, "oblique_samples": build.oblique_samples}
    if field is not None:
        out.update(field_report(field, loop.scenario.eye, build.coverage.view().angle_from_data_rad, n_grid))
    out["sigma_calibration"] = getattr(field, "sigma_calibration", None)
    out["on_the_way"] = build.honesty  # the field's sigma during the build (BuildHonesty.summary; None without one)
    return out


def update_timing(loop) -> dict | None:
    """The model update's wall time per A-scan over the loop's last run (us: each sensor
    packet's update over its valid samples): median, p99, max; None without updates."""
    us = np.asarray(loop.model.update_us, dtype=float)
    if not len(us):
        return None
    return {"median": float(np.median(us)), "p99": float(np.percentile(us, 99)), "max": float(us.max())}


def error_sigma_figure(loop, build, n_grid: int = 120):
    """The model's exact error and standard deviation (um) over the retina's reference
    region, as maps in azimuth and elevation seen from the eye centre, with the measured
    directions; a matplotlib Figure (None for the prior)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kind, field = filter_model(loop, build)
    if field is None:
        return None
    eye, c = loop.scenario.eye, loop.scenario.eye_pose.p_WE
    T = eye.reference_samples(n_grid, n_grid)
    err = 1e3 * np.abs(field.signed_distance(T))
    sigma = 1e3 * np.asarray(field.uncertainty(T), dtype=float)
    V = loop.scenario.eye_pose.to_E(T) - loop.scenario.eye_pose.to_E(c[None])[0]
    az, el = np.degrees(np.arctan2(V[:, 0], -V[:, 2])), np.degrees(np.arctan2(V[:, 1], np.hypot(V[:, 0], V[:, 2])))
    D = build.coverage.view().sorted_directions
    DE = loop.scenario.eye_pose.to_E(c[None] + D) - loop.scenario.eye_pose.to_E(c[None])[0]
    fig, axes = plt.subplots(1, 2, figsize=(12, 5), constrained_layout=True)
    for ax, val, title in ((axes[0], err, "exact error (um)"), (axes[1], sigma, "standard deviation sigma (um)")):
        v = np.where(np.isfinite(val), np.clip(val, 1.0, None), np.nan)  # non-finite (no bound there): grey
        lo = float(np.nanmin(v)) if np.isfinite(v).any() else 1.0
        hi = max(float(np.nanmax(v)) if np.isfinite(v).any() else 10.0, 10.0 * lo)
        cmap = matplotlib.colormaps["viridis"].with_extremes(bad="lightgrey")
        sc = ax.scatter(az, el, c=v, s=4, cmap=cmap, norm=matplotlib.colors.LogNorm(lo, hi), plotnonfinite=True)
        ax.scatter(np.degrees(np.arctan2(DE[:, 0], -DE[:, 2])), np.degrees(np.arctan2(DE[:, 1], np.hypot(DE[:, 0], DE[:, 2]))),
                   s=1, c="r", alpha=0.3, label="measured directions")
        fig.colorbar(sc, ax=ax)
        ax.set_xlabel("azimuth from the posterior pole, temporal + (deg)")
        ax.set_ylabel("elevation (deg)")
        ax.set_title(f"{title}, {kind} model")
    axes[0].legend(loc="lower right", markerscale=6)
    return fig
