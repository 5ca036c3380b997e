"""Figures of the paper experiment: Fig. 5 (MAE over the spiral with the transition)."""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from eval.experiments.paper import ACCURACY_REQUIRED_MM

_CRITERION_STYLE = {"scan_range": ("tab:purple", ":"), "residual": ("tab:brown", ":"), "temporal": ("tab:pink", ":")}


def fig5(shape: str, fractions, sf_mae_mm, ef_mae_mm, paper_met_at: dict, transition_at, optimal_at, criterion: str,
         n_seeds: int, local_mae_mm=None, local_at=None):
    """The paper's Fig. 5 for one shape: SF and EF MAE (mm, log scale) over spiral
    completion, the local model's (models.local) and where it was taken up, each paper criterion's first-met point, the optimal and the actual
    transition, sphere/ellipsoid phases shaded, the 0.5 mm accuracy line."""
    fig, ax = plt.subplots(figsize=(8, 4.5))
    x = 100 * np.asarray(fractions)
    end = 100.0
    switch = None if transition_at is None else 100 * transition_at
    ax.axvspan(0, switch if switch is not None else end, color="tab:blue", alpha=0.06, label="sphere phase")
    if switch is not None:
        ax.axvspan(switch, end, color="tab:orange", alpha=0.08, label="ellipsoid phase")
        ax.axvline(switch, color="k", lw=1.6, label=f"transition ({criterion} criteria)")
    ax.plot(x, sf_mae_mm, color="tab:blue", lw=1.8, label="sphere fit MAE")
    ax.plot(x, ef_mae_mm, color="tab:orange", lw=1.8, label="ellipsoid fit MAE")
    if local_mae_mm is not None:
        ax.plot(x, local_mae_mm, color="tab:cyan", lw=1.8, label="local model MAE")
        if local_at is not None:
            ax.axvline(100 * local_at, color="tab:cyan", lw=1.2, ls="--", label="local model used")
    ax.axhline(ACCURACY_REQUIRED_MM, color="tab:red", ls="--", lw=1, label="0.5 mm required accuracy")
    if optimal_at is not None:
        ax.axvline(100 * optimal_at, color="tab:green", lw=1.4, ls="-.", label="optimal transition")
    for name, at in paper_met_at.items():
        if at is not None:
            color, ls = _CRITERION_STYLE.get(name, ("gray", ":"))
            ax.axvline(100 * at, color=color, ls=ls, lw=1.2, label=f"paper criterion met: {name}")
    ax.set_yscale("log")
    ax.set_xlim(0, end)
    ax.set_xlabel("spiral completion (%)")
    ax.set_ylabel("MAE to ground truth (mm, exact)")
    seeds = f", mean of {n_seeds} noise seeds" if n_seeds > 1 else ""
    ax.set_title(f"{shape}: model accuracy along the spiral{seeds}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=3, frameon=False)
    return fig
