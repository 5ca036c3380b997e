"""`vitreoguard boundary --shape all`: the boundary campaign on all six eyes in one command.

The shapes run one after the other, each in a process forked for it from this one (which
builds nothing itself), its scenarios on all the workers (--jobs processes forked from
the shape's process, which built the shape's loop, or Ray). Measured on 2 cores (6 x 1,000
scenarios): 160 s this way, as six separate commands take; 202 s with every shape in this
one process (the earlier shapes' loops and results stay in the heap the workers fork and
the collector scans); 240 s with two shapes at a time in their own processes (--jobs 1
each), although that overlaps one shape's serial phases with the other's scenarios:
forked workers share their parent's loop, kernels and eye clouds in memory, two
independent processes do not, and each ran 25 % slower. Each shape writes what `boundary --shape S` writes, into OUT/S;
OUT/summary.json holds every shape's headline figures and the wall time. One progress bar
counts the scenarios of all shapes.
"""
from __future__ import annotations

import json
import multiprocessing
import os
import queue
import time
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
    table and writes OUT/summary.json. Returns the exit code (1 when a shape failed)."""
    if args.eye_param:
        raise UsageError("--eye-param needs one --shape (the parameters are a shape's), not --shape all")
    out = prepare_out_dir(args.out)
    total = len(ORDER) * (args.scenarios + args.sphere_scenarios)
    t0 = time.perf_counter()
    workers = Workers(jobs=args.jobs, ray=getattr(args, "ray", None))
    with progress_bar(total, f"scenarios of {len(ORDER)} shapes", unit="scenario") as bar:
        codes = _in_turn(args, one_shape, out, workers, bar)
    wall = time.perf_counter() - t0
    rows = {s: {k: json.loads((out / s / "boundary.json").read_text()).get(k) for k in HEADLINE} if codes[s] == 0
            else None for s in ORDER}
    write_json(out / "summary.json", {"shapes": rows, "wall_s": wall, "jobs": args.jobs, "ray": workers.ray,
                                      "seed": args.seed, "exit_codes": codes})
    print(f"{'shape':12s} {'scenarios':>9s} {'violations':>10s} {'contacts':>8s} {'min true clearance (mm)':>24s}")
    for s, r in rows.items():
        if r is None:
            print(f"{s:12s} failed (exit {codes[s]}): see {out / s}")
        else:
            print(f"{s:12s} {r['scenarios']:9d} {r['violations']:10d} {r['contacts']:8d} {r['min_true_clearance_mm']:24.4f}")
    print(f"all shapes in {wall:.1f} s wall on {workers.describe()}; wrote {out / 'summary.json'} and one folder per shape")
    return 0 if all(c == 0 for c in codes.values()) else 1


def _shape_args(args, shape: str) -> Namespace:
    return Namespace(**{**vars(args), "shape": shape, "out": str(os.path.join(args.out, shape)), "eye_params": {}})


def _in_turn(args, one_shape, out, workers, bar) -> dict:
    """Each shape in a forked process of its own, one at a time, its scenarios on `workers`
    (with Ray: in this process, Ray's client is not fork-safe): {shape: exit code}."""
    if workers.ray is not None:
        for s in ORDER:
            one_shape(_shape_args(args, s), out / s, workers, bar.update)
        return dict.fromkeys(ORDER, 0)
    ctx = multiprocessing.get_context("fork")
    done_q, codes = ctx.Queue(), {}
    for s in ORDER:
        p = ctx.Process(target=_child, args=(one_shape, _shape_args(args, s), out / s, workers, done_q),
                        name=f"boundary {s}")
        p.start()
        try:
            while p.is_alive() or not done_q.empty():
                try:
                    bar.update(done_q.get(timeout=0.25))
                except queue.Empty:
                    pass
        finally:  # Ctrl-C or an error here: the shape does not run on
            if p.is_alive():
                p.terminate()
            p.join()
        codes[s] = p.exitcode
    return codes


def _child(one_shape, args, out, workers, done_q) -> None:
    os.environ[ENV_DISABLE] = "1"  # the parent's bar counts this shape's scenarios
    one_shape(args, out, workers, done_q.put)
