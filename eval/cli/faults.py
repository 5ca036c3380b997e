"""`vitreoguard faults`: the boundary under real-robot faults, one campaign per class.

For each fault class (eval.experiments.faults: actuator delay, lag and acceleration
limit, calibration error at the declared bound, OCT time offset, encoder noise, dropped,
frozen and invalid streams, floaters, and all but the stream faults at once, "combined";
"ideal" and "none" for reference) builds the model by the
spiral through the faulty loop and runs the boundary's adversarial campaign against it.
Writes faults.json ({"model": the model that bounds the motion, "local" or "quadric" (as
boundary.json's loop.model), "classes": {name: {"parameters", "scenarios", "violations",
"contacts", "min_true_clearance_mm", "failsafe_stops", "stops_by_reason",
"infeasible_qp_stops", "model": the filter's model's figures, ...}}, "margin_costs_mm":
{name: mm}}) and faults.png (each class's
smallest true clearance per scenario); with `--shape all` the same per shape under
"shapes" and one faults_<shape>.png each.
"""
from __future__ import annotations

from eval.cli.args import SEED, add_eye_param, choice, eye_params, integer, number, out_dir
from eval.cli.io import UsageError, prepare_out_dir, save_figure, write_json
from eval.cli.loop_flags import CALIBRATION_BOUND, add_model_flag
from eval.cli.progress import progress_bar
from eval.cli.workers import add_worker_flags, workers_of
from eval.interrupts import is_interrupt
from models.eyes import EYE_SHAPES

SCENARIOS = integer(1, 100_000)
DURATION_S = number(0.05, 10.0, "s")


def register(sub) -> None:
    from eval.experiments.faults import FAULT_CLASSES

    p = sub.add_parser("faults", help="adversarial campaigns under real-robot faults: faults.json, faults.png")
    p.add_argument("--shape", type=choice("shape", (*EYE_SHAPES, "all")), default="emmetropic",
                   help=f"true eye: one of {' '.join(EYE_SHAPES)}; all: each in turn")
    p.add_argument("--scenarios", type=SCENARIOS, default=100, help=f"adversarial scenarios per class, {SCENARIOS.range}")
    p.add_argument("--seed", type=SEED, default=0, help=f"seed of starts, adversaries and sensor noise, {SEED.range}")
    p.add_argument("--duration-s", type=DURATION_S, default=0.5, help=f"length of one scenario, {DURATION_S.range}")
    p.add_argument("--classes", default="all",
                   help=f"comma-separated fault classes, of {', '.join(FAULT_CLASSES)}; all: every one")
    p.add_argument("--calibration-bound", type=CALIBRATION_BOUND, default=None, metavar="MM,DEG",
                   help=f"declared calibration bound the filter keeps, {CALIBRATION_BOUND.range}; default 0.03,0.13")
    add_eye_param(p)
    add_model_flag(p)
    p.add_argument("--out", type=out_dir, default="out/faults", help="output directory")
    add_worker_flags(p)
    p.set_defaults(func=main)


def classes_of(text: str) -> list:
    from eval.experiments.faults import FAULT_CLASSES

    if text.strip() == "all":
        return list(FAULT_CLASSES)
    names = [c.strip() for c in text.split(",")]
    if "" in names:
        raise UsageError(f"--classes: an empty class name in {text!r}; comma-separated names of "
                         f"{','.join(FAULT_CLASSES)}")
    bad = [c for c in names if c not in FAULT_CLASSES]
    if bad:
        raise UsageError(f"--classes: unknown class {bad[0]!r}; choose from {','.join(FAULT_CLASSES)}")
    return list(dict.fromkeys(names))


def main(args) -> int:
    from eval.cli.loop_flags import loop_config

    names = classes_of(args.classes)
    if args.eye_param and args.shape == "all":
        raise UsageError("--eye-param needs one --shape (the parameters are a shape's), not --shape all")
    params = {} if args.shape == "all" else eye_params(args.eye_param, args.shape)
    workers = workers_of(args)
    out = prepare_out_dir(args.out)
    base = loop_config(args)
    shapes = list(EYE_SHAPES) if args.shape == "all" else [args.shape]
    per_shape = {}
    for shape in shapes:
        per_shape[shape] = _shape_classes(args, shape, params, names, base, workers)
        save_figure(_figure(per_shape[shape]["classes"], shape),
                    out / ("faults.png" if len(shapes) == 1 else f"faults_{shape}.png"))
    result = {"seed": args.seed, "scenario_s": args.duration_s, "violation_threshold_mm": 0.45,
              "model": "local" if base.local_model else "quadric", "eye_params": params,
              "calibration_bound": [base.filter.calibration_bound_mm, base.filter.calibration_bound_deg]}
    if len(shapes) == 1:
        result = {"shape": shapes[0], **result, **per_shape[shapes[0]]}
    else:
        result["shapes"] = per_shape
    write_json(out / "faults.json", result)
    print(f"wrote {out / 'faults.json'} and the plots in {out}")
    return 0


def _shape_classes(args, shape: str, params: dict, names: list, base, workers) -> dict:
    """{"classes": {name: faults.json entry}, "margin_costs_mm": ...} on one eye shape (with
    make_eye's shape parameters `params`)."""
    from eval.cli.boundary import bar_progress, make_loop
    from eval.experiments.faults import fault_class, margin_costs, run_fault_class

    classes = {}
    for name in names:
        fc = fault_class(name, base)
        with progress_bar(args.scenarios, f"{shape} {name}: adversarial scenarios", unit="scenario") as bar:
            try:
                classes[name] = run_fault_class(fc, shape, args.scenarios, args.seed, args.duration_s, make_loop,
                                                progress=bar_progress(bar), workers=workers, eye_params=params)
            except RuntimeError as exc:  # e.g. the model this loop built leaves too few reachable starts
                if is_interrupt(exc):
                    raise
                classes[name] = {"parameters": fc.parameters, "error": str(exc)}
                print(f"{shape:10s} {name:14s} not run: {exc}")
                continue
        c = classes[name]
        worst = c.get("detection_ms", {}).get("max")
        detection = "" if "detection_ms" not in c else \
            f"  detection max {'-' if worst is None else f'{worst:.1f}'} ms, undetected {c['detection_ms']['undetected']}"
        print(f"{shape:10s} {name:14s} model {c['model']['kind']} MAE {c['model']['mae_um']:.0f} um"
              f"  violations {c['violations']:3d}  contacts {c['contacts']:3d}"
              f"  min {c['min_true_clearance_mm']:.3f} mm  infeasible {c['infeasible_qp_stops']}  held {c.get('recovery_held_steps', 0)}  eased {c.get('correction_eased_steps', 0)}"
              f"  stops {c['failsafe_stops']:3d} {c['stops_by_reason']}{detection}")
    return {"classes": classes, "margin_costs_mm": margin_costs(classes)}


def _figure(classes: dict, shape: str):
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(max(6, 0.9 * len(classes) + 2), 4))
    rng = np.random.default_rng(0)
    for i, (name, c) in enumerate(classes.items()):
        if "error" in c:
            ax.text(i, 0.5, "not run", rotation=90, ha="center", va="bottom", color="gray")
            continue
        mins = np.asarray(c["min_clearance_per_run"])
        ax.scatter(i + rng.uniform(-0.25, 0.25, len(mins)), mins, s=6, alpha=0.5,
                   color="tab:red" if c["violations"] else "tab:blue")
        ax.plot([i - 0.35, i + 0.35], [mins.min()] * 2, color="k", lw=1)
    ax.axhline(0.5, color="k", ls=":", lw=1, label="boundary (0.5 mm)")
    ax.axhline(0.45, color="r", ls="--", lw=1, label="violation (0.45 mm)")
    ax.set_xticks(range(len(classes)), list(classes), rotation=30, ha="right")
    ax.set_ylabel("smallest TRUE clearance per scenario (mm)")
    ax.set_title(f"{shape}: adversarial scenarios per fault class (black: the class's minimum)")
    ax.legend(loc="upper right")
    fig.tight_layout()
    return fig
