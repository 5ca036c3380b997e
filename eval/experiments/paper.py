"""The paper's simulation experiment (Table 2, Fig. 5) on one eye shape and noise seed.

The scan is the `paper` scenario (models.scan.paper_scan); the points go one A-scan at a
time into AdaptiveEyeModel. Errors are in mm, positions along the scan are fractions
of the spiral in [0, 1] (point index / number of points).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from models import AdaptiveEyeModel, Ellipsoid
from models.adaptive.outlier_gate import OutlierGate
from models.adaptive.transition import CRITERIA, PaperCriteria
from models.eyes import EyePose, make_eye
from models.fit.robust_fit import RobustFitConfig
from models.local.grid import LocalRetinaModel
from models.local.field import LocalField
from models.metrics import MeanSD, PaperMetrics, SigmaHonesty, distances_and_sigmas, mae_exact, paper_metrics
from models.scan.paper_scan import paper_scan

# Table 2 of the paper (simulation), mm: mean, SD.
PAPER_TABLE2 = {
    "emmetropic": {"mmae": [0.041, 0.016], "sf_fmae": [0.079, 0.040], "sf_mae": [0.244, 0.277], "ef_fmae": [0.038, 0.015], "ef_mae": [0.035, 0.016]},
    "myopic": {"mmae": [0.043, 0.016], "sf_fmae": [0.078, 0.039], "sf_mae": [0.147, 0.123], "ef_fmae": [0.040, 0.016], "ef_mae": [0.038, 0.016]},
    "hyperopic": {"mmae": [0.039, 0.015], "sf_fmae": [0.099, 0.052], "sf_mae": [0.309, 0.355], "ef_fmae": [0.036, 0.014], "ef_mae": [0.033, 0.015]},
    "pointed": {"mmae": [0.068, 0.045], "sf_fmae": [0.178, 0.138], "sf_mae": [0.401, 0.285], "ef_fmae": [0.569, 0.114], "ef_mae": [0.744, 0.293]},
    "detached": {"mmae": [0.043, 0.016], "sf_fmae": [0.090, 0.049], "sf_mae": [0.147, 0.127], "ef_fmae": [0.043, 0.022], "ef_mae": [0.061, 0.070]},
    "staphyloma": {"mmae": [0.043, 0.016], "sf_fmae": [0.098, 0.066], "sf_mae": [0.168, 0.161], "ef_fmae": [0.069, 0.057], "ef_mae": [0.232, 0.287]},
}
PAPER_LAG_RANGE = (0.219, 0.378)  # transition after the optimal one, fraction of the spiral
ACCURACY_REQUIRED_MM = 0.5  # the paper's required model accuracy (MAE)


@dataclass
class ShapeRun:
    """Everything one (shape, seed) run measured. Curves are sampled at `fractions`."""

    shape: str
    seed: int
    n_points: int
    fractions: np.ndarray
    sf_mae_curve: np.ndarray
    ef_mae_curve: np.ndarray
    sf: PaperMetrics
    ef: PaperMetrics
    optimal_transition_at: float | None
    lc_mae_curve: np.ndarray | None = None  # the local model's (models.local), the first criterion's model
    lc: PaperMetrics | None = None
    local_at: float | None = None  # fraction of the spiral at which the local correction was last taken up
    globe_mae_curve: np.ndarray | None = None  # the robust globe's (models.fit.streaming_robust), NaN before its fit
    # the local model's sigma against its true error along the spiral (models.metrics.SigmaHonesty; NaN before a global
    # model): the fraction of the curve's reference samples within 3 sigma, the fraction beyond 3 sigma on the unsafe
    # side (the model's retina beyond the true one) and the largest such excess (mm)
    lc_coverage_curve: np.ndarray | None = None
    lc_unsafe_curve: np.ndarray | None = None
    lc_excess_curve: np.ndarray | None = None
    global_ellipsoid_at: float | None = None  # from here on the local part's global quadric is an ellipsoid (None: ends a sphere)
    transitions: dict = field(default_factory=dict)  # criterion name -> fraction or None
    criteria_met_at: dict = field(default_factory=dict)  # criterion name -> {name: fraction or None}
    history: list | None = None  # ModelUpdate per A-scan (run_shape(keep_history=True))


def first_met(history, name: str) -> int | None:
    """Index of the first history entry where criterion `name` is met, or None."""
    return next((i for i, u in enumerate(history) if u.criteria[name][1]), None)


def optimal_transition(fractions: np.ndarray, sf_mae: np.ndarray, ef_mae: np.ndarray) -> float | None:
    """First fraction after which the EF MAE stays below the SF MAE (None if never)."""
    better = ef_mae < sf_mae
    if not better[-1]:
        return None
    last_worse = np.flatnonzero(~better)
    return float(fractions[0] if len(last_worse) == 0 else fractions[last_worse[-1] + 1])


def run_shape(
    shape: str,
    seed: int = 0,
    noise_um: float = 20.0,
    pose: EyePose | None = None,
    stride: int = 1,
    n_curve: int = 100,
    grid: int = 500,
    criteria: tuple[str, ...] = ("paper", "predictive"),
    keep_history: bool = False,
    robust: RobustFitConfig | None = None,
    eye_params: dict | None = None,
) -> ShapeRun:
    """Scan `shape` along the paper's spiral (every `stride`-th A-scan), fit with each
    transition criterion in `criteria`, and measure Table 2 and the Fig. 5 curves.

    `n_curve` MAE points along the spiral (each on a 60 x 60 ground-truth sampling);
    `grid` x `grid` sampling for the final Table 2 metrics (the paper: 500).
    The first criterion's model carries the local part; its global quadric
    (AdaptiveEyeModel.global_for_local: the least-squares ellipsoid, the robust globe or
    the eye globe, else the sphere) is followed along the curve (`global_ellipsoid_at`), with the robust
    globe's MAE (`globe_mae_curve`), and so is the honesty of the local model's sigma
    (`lc_coverage_curve`, `lc_unsafe_curve`, `lc_excess_curve`: models.metrics.SigmaHonesty).
    `keep_history` keeps the model history (of the first criterion) in the result;
    `robust`: None for the paper's least-squares ellipsoid, else the robust fit's
    settings (models.fit.robust_fit); `eye_params`: make_eye's shape parameters.
    """
    eye = make_eye(shape, pose, **(eye_params or {}))
    scan = paper_scan(eye, noise_um=noise_um, seed=seed)
    points, beams = scan.points[:: int(stride)], scan.beam_W[:: int(stride)]
    n = len(points)
    # consecutive points of a thinned scan lie `stride` times further apart
    gate = OutlierGate(max_jump_mm=OutlierGate().max_jump_mm * stride)
    # the local model rides on the first criterion's model (the global fits do not depend on the criterion; the
    # quadric under the local part does: AdaptiveEyeModel.global_for_local)
    models = {name: AdaptiveEyeModel(CRITERIA[name](), gate, robust, LocalRetinaModel(eye.pose.p_WE) if i == 0 else None)
              for i, name in enumerate(criteria)}
    first = next(iter(models.values()))
    scans_c = np.unique(np.linspace(1, n, n_curve).round().astype(int))
    curve_truth = eye.reference_samples(60, 60)
    lc_curve, honesty, globe_curve, local_at, was_local = {}, {}, {}, None, False
    global_ellipsoid_at, was_ellipsoid = None, False
    for i, (p, beam) in enumerate(zip(points, beams)):
        for m in models.values():
            m.update(p, beam)
        if first.level == "local" and not was_local:
            local_at = (i + 1) / n
        was_local = first.level == "local"
        if i + 1 in scans_c:
            if first.local.global_params is not None:
                lc_field = LocalField(first.local.params(was_local))
                signed, sigma = distances_and_sigmas(lc_field, curve_truth)  # once for the MAE and the honesty
                lc_curve[i + 1] = MeanSD.of(signed).mean
                honesty[i + 1] = SigmaHonesty.of(signed, sigma)
            globe = first.globe.last_ok
            globe_curve[i + 1] = np.nan if globe is None else mae_exact(globe.ellipsoid, curve_truth).mean
            is_ellipsoid = isinstance(first.global_for_local(), Ellipsoid)
            if is_ellipsoid and not was_ellipsoid:
                global_ellipsoid_at = (i + 1) / n
            was_ellipsoid = is_ellipsoid
    history = next(iter(models.values())).history  # fits do not depend on the criterion
    received = np.array([u.n_received for u in history])
    scans = np.unique(np.linspace(1, n, n_curve).round().astype(int))  # A-scans received
    entry = np.searchsorted(received, scans, side="right") - 1  # the model after that A-scan
    ok = (entry >= 0) & np.array([e >= 0 and history[e].ellipsoid_center is not None and history[e].sphere_center is not None for e in entry])
    scans, entry = scans[ok], entry[ok]
    sf_curve = np.array([mae_exact(history[e].sphere, curve_truth).mean for e in entry])
    ef_curve = np.array([mae_exact(history[e].ellipsoid, curve_truth).mean for e in entry])
    fractions = scans / n
    truth = eye.reference_samples(grid, grid)
    final = history[-1]
    run = ShapeRun(
        shape=shape,
        seed=seed,
        n_points=n,
        fractions=fractions,
        sf_mae_curve=sf_curve,
        ef_mae_curve=ef_curve,
        sf=paper_metrics(final.sphere, eye, points, grid, truth),
        ef=paper_metrics(final.ellipsoid, eye, points, grid, truth),
        optimal_transition_at=optimal_transition(fractions, sf_curve, ef_curve),
        history=history if keep_history else None,
        lc_mae_curve=np.array([lc_curve.get(int(k), np.nan) for k in scans]),
        local_at=local_at if first.level == "local" else None,
        globe_mae_curve=np.array([globe_curve.get(int(k), np.nan) for k in scans]),
        **{f"lc_{name}_curve": np.array([getattr(honesty[int(k)], attr) if int(k) in honesty else np.nan for k in scans])
           for name, attr in (("coverage", "coverage"), ("unsafe", "unsafe_fraction"), ("excess", "worst_excess_mm"))},
        global_ellipsoid_at=global_ellipsoid_at if was_ellipsoid else None,
    )
    first.local.solve_all()
    lc_field = LocalField(first.local.params(first.level == "local"), first.level)
    run.lc = paper_metrics(lc_field, eye, points, grid, truth)
    for name, m in models.items():
        at = lambda i: None if i is None else m.history[i].n_received / n  # noqa: E731
        run.transitions[name] = at(m.transition_index)
        run.criteria_met_at[name] = {c: at(first_met(m.history, c)) for c in m.criteria.names}
    return run


MAX_LAG = 0.10  # target: switch within 10 % of the spiral after the optimal point


def best_ellipsoid_curve(ef_mae: np.ndarray, globe_mae: np.ndarray) -> np.ndarray:
    """The MAE of the better of the least-squares ellipsoid and the robust globe at each
    point of the curves (either alone where the other has no fit yet)."""
    return np.fmin(ef_mae, globe_mae)


def decision(transition_at: float | None, optimal_at: float | None) -> dict:
    """{"transition_at", "lag" (transition - optimal, fraction), "decision_right", "timely"}:
    right when the model switches exactly for the shapes whose optimal transition exists;
    timely when, besides, it switches no earlier than the optimum and within MAX_LAG."""
    lag = None if transition_at is None or optimal_at is None else transition_at - optimal_at
    right = (transition_at is None) == (optimal_at is None)
    timely = right and (lag is None or 0.0 <= lag <= MAX_LAG)
    return {"transition_at": transition_at, "lag": lag, "decision_right": right, "timely": timely}


__all__ = ["PAPER_TABLE2", "PaperCriteria", "ShapeRun", "decision", "optimal_transition", "run_shape"]
