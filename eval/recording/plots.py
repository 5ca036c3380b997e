"""The fit's figures: the synchronisation (sync.png) and the model against the points (fit.png)."""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np


def figure_sync(result):
    """(a) residual RMS of the synchronisation fit over the trial offsets, the estimate
    marked; (b) the measured distance over the segment and the robot's travel mapped by
    the fit (c + g s(t - offset)) at the estimate."""
    est, joints, oct = result.offset, result.joints, result.oct
    i0, i1 = result.segment
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(13, 4.2))
    ax1.plot(1e3 * est.grid_s, 1e3 * est.grid_rms_mm, color="tab:blue", lw=1.2)
    ax1.axvline(1e3 * est.offset_s, color="tab:red", ls="--", lw=1, label=f"estimate {1e3 * est.offset_s:+.3f} ms")
    ax1.set_xlabel("trial time offset, OCT minus robot clock (ms)")
    ax1.set_ylabel("residual RMS (um)")
    ax1.set_yscale("log")
    ax1.set_title("(a) synchronisation fit over the trial offsets")
    ax1.legend(fontsize=8)
    t0, t1 = joints.t_s[i0], joints.t_s[i1 - 1]
    inside = (oct.t_s >= t0) & (oct.t_s <= t1)
    s = result.sync_travel_mm
    ax2.plot(oct.t_s[inside] - t0, oct.distance_mm[inside], ".", ms=1.5, color="0.3", label="measured distance (OCT clock)")
    ax2.plot(joints.t_s[i0:i1] + est.offset_s - t0, est.constant_mm + est.gain * s, color="tab:red", lw=0.8,
             label="robot travel, shifted by the estimate")
    ax2.set_xlabel("time in the segment (s)")
    ax2.set_ylabel("distance to the retina (mm)")
    ax2.set_title(f"(b) the segment: gain {est.gain:+.3f}, residual {1e3 * est.residual_rms_mm:.1f} um RMS")
    ax2.legend(fontsize=8)
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def figure_fit(result):
    """(a) the points and the fitted model in the model's frame, seen along its first
    axis (the points coloured by their signed distance to the model, um); (b) the
    histogram of those distances."""
    model = result.model.shape
    P = result.accepted
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 5))
    if model is None or not len(P):
        ax1.text(0.5, 0.5, "no model", ha="center")
        return fig
    R = getattr(model, "rotation", np.eye(3))
    L = (P - model.center) @ R
    sd = 1e3 * model.signed_distance(P)
    lim = max(float(np.percentile(np.abs(sd), 99)), 1.0)
    sc = ax1.scatter(L[:, 1], L[:, 2], c=sd, s=1, cmap="coolwarm", vmin=-lim, vmax=lim)
    t = np.linspace(0, 2 * np.pi, 400)
    radii = getattr(model, "radii", np.full(3, getattr(model, "radius", 1.0)))
    ax1.plot(radii[1] * np.cos(t), radii[2] * np.sin(t), color="k", lw=0.8, label=f"{result.model.kind} (its x = 0 section)")
    ax1.set_aspect("equal")
    ax1.set_xlabel("model axis 2 (mm)")
    ax1.set_ylabel("model axis 3 (mm)")
    ax1.set_title(f"(a) {len(P)} points, model {result.model.kind}")
    ax1.legend(fontsize=8, loc="upper right")
    fig.colorbar(sc, ax=ax1, label="signed distance to the model (um, > 0 inside)")
    ax2.hist(sd, bins=80, color="tab:blue")
    ax2.set_xlabel("signed distance of a point to the model (um)")
    ax2.set_ylabel("points")
    ax2.set_title(f"(b) FMAE {np.mean(np.abs(sd)):.1f} um")
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    return fig
