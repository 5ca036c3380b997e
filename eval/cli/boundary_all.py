"""`vitreoguard boundary --shape all`: the boundary campaign on all six eyes in one command.

The shapes run one after the other in this process, each shape's scenarios on all the
workers (--jobs processes forked from the process that built the shape's loop, or Ray).
Measured on 2 cores (6 x 1,000 scenarios): 160 s this way; 240 s with two shapes at a
time in their own processes (--jobs 1 each), although that overlaps one shape's serial
phases (spiral, plots) with the other's scenarios: forked workers share their parent's
loop, kernels and eye clouds in memory, two independent processes do not, and each ran
25 % slower. Each shape writes what `boundary --shape S` writes, into OUT/S;
OUT/summary.json holds every shape's headline figures and the wall time. One progress bar
counts the scenarios of all shapes.
"""
from __future__ import annotations

import os
import time
from contextlib import contextmanager
from argparse import Namespace

from eval.cli.io import UsageError, prepare_out_dir, write_json
from eval.cli.progress import ENV_DISABLE, progress_bar
from eval.experiments.campaign import Workers
from models.eyes import EYE_SHAPES

ALL = "all"
ORDER = EYE_SHAPES
HEADLINE = ("scenarios", "violations", "contacts", "min_true_clearance_mm", "failsafe_stops", "realtime_factor")


def run_all(args, one_shape) -> int:
    """Run `one_shape(args_for_shape, out_dir, workers, progress)` (boundary's run and
    write of one shape; `progress(n)` after n more scenarios) for every shape; prints a
    table and writes OUT/summary.json. Returns the exit code 0."""
    if args.eye_param:
        raise UsageError("--eye-param needs one --shape (the parameters are a shape's), not --shape all")
    out = prepare_out_dir(args.out)
    total = len(ORDER) * (args.scenarios + args.sphere_scenarios)
    t0 = time.perf_counter()
    workers = Workers(jobs=args.jobs, ray=getattr(args, "ray", None))
    with progress_bar(total, f"scenarios of {len(ORDER)} shapes", unit="scenario") as bar, _quiet():
        results = {s: one_shape(_shape_args(args, s), out / s, workers, bar.update) for s in ORDER}
    wall = time.perf_counter() - t0
    rows = {s: {k: r.get(k) for k in HEADLINE} for s, r in results.items()}
    write_json(out / "summary.json", {"shapes": rows, "wall_s": wall, "jobs": args.jobs, "ray": workers.ray,
                                      "seed": args.seed})
    print(f"{'shape':12s} {'scenarios':>9s} {'violations':>10s} {'contacts':>8s} {'min true clearance (mm)':>24s}")
    for s, r in rows.items():
        print(f"{s:12s} {r['scenarios']:9d} {r['violations']:10d} {r['contacts']:8d} {r['min_true_clearance_mm']:24.4f}")
    print(f"all shapes in {wall:.1f} s wall on {workers.describe()}; wrote {out / 'summary.json'} and one folder per shape")
    return 0


def _shape_args(args, shape: str) -> Namespace:
    return Namespace(**{**vars(args), "shape": shape, "out": str(os.path.join(args.out, shape)), "eye_params": {}})


@contextmanager
def _quiet():
    """The shapes' own bars and phases off while the bar over all shapes runs."""
    old = os.environ.get(ENV_DISABLE)
    os.environ[ENV_DISABLE] = "1"
    try:
        yield
    finally:
        if old is None:
            del os.environ[ENV_DISABLE]
        else:
            os.environ[ENV_DISABLE] = old
