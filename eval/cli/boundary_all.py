"""`vitreoguard boundary --shape all`: the boundary campaign on all six eyes in one command.

The shapes run in `lanes` forked processes at a time (lanes = min(--jobs, 6); each shape's
scenarios on --jobs // lanes workers of its own), the longest first: one shape's serial
phases (its spiral, its figures) overlap the others' scenarios, which keeps the cores busy
where shapes one after the other would leave one idle. Each shape writes what
`boundary --shape S` writes, into OUT/S; OUT/summary.json holds every shape's headline
figures and the wall time. One progress bar counts the scenarios of all shapes.
With --ray the shapes run one after the other, their scenarios on Ray.
"""
from __future__ import annotations

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
ORDER = ("pointed", "staphyloma", "detached", "hyperopic", "myopic", "emmetropic")  # slowest first (measured)
HEADLINE = ("scenarios", "violations", "contacts", "min_true_clearance_mm", "failsafe_stops", "realtime_factor")


def run_all(args, one_shape) -> int:
    """Run `one_shape(args_for_shape, out_dir, workers, progress)` (boundary's run and
    write of one shape; `progress(n)` after n more scenarios) for every shape; prints a
    table and writes OUT/summary.json. Returns the exit code (1 when a shape failed)."""
    if args.eye_param:
        raise UsageError("--eye-param needs one --shape (the parameters are a shape's), not --shape all")
    assert sorted(ORDER) == sorted(EYE_SHAPES)
    out = prepare_out_dir(args.out)
    total = len(ORDER) * (args.scenarios + args.sphere_scenarios)
    t0 = time.perf_counter()
    with progress_bar(total, f"scenarios of {len(ORDER)} shapes", unit="scenario") as bar:
        if getattr(args, "ray", None) is not None:
            workers = Workers(jobs=args.jobs, ray=args.ray)
            codes = {s: _call(one_shape, _shape_args(args, s), out / s, workers, bar.update) for s in ORDER}
        else:
            codes = _lanes(args, one_shape, out, bar)
    wall = time.perf_counter() - t0
    rows = {}
    for s in ORDER:
        path = out / s / "boundary.json"
        rows[s] = None
        if codes[s] == 0 and path.is_file():
            import json

            rows[s] = {k: json.loads(path.read_text()).get(k) for k in HEADLINE}
    write_json(out / "summary.json", {"shapes": rows, "wall_s": wall, "jobs": args.jobs,
                                      "seed": args.seed, "exit_codes": codes})
    print(f"{'shape':12s} {'scenarios':>9s} {'violations':>10s} {'contacts':>8s} {'min true clearance (mm)':>24s}")
    for s, r in rows.items():
        if r is None:
            print(f"{s:12s} failed (exit {codes[s]}): see {out / s}")
        else:
            print(f"{s:12s} {r['scenarios']:9d} {r['violations']:10d} {r['contacts']:8d} {r['min_true_clearance_mm']:24.4f}")
    print(f"all shapes in {wall:.1f} s wall on {args.jobs} job(s); wrote {out / 'summary.json'} and one folder per shape")
    return 0 if all(c == 0 for c in codes.values()) else 1


def _shape_args(args, shape: str) -> Namespace:
    return Namespace(**{**vars(args), "shape": shape, "out": str(os.path.join(args.out, shape)), "eye_params": {}})


def _call(one_shape, args, out, workers, progress) -> int:
    one_shape(args, out, workers, progress)
    return 0


def _lanes(args, one_shape, out, bar) -> dict:
    """The shapes in forked processes, `lanes` at a time: {shape: exit code}."""
    lanes = max(1, min(args.jobs, len(ORDER)))
    inner = Workers(jobs=max(1, args.jobs // lanes))
    ctx = multiprocessing.get_context("fork")
    done_q = ctx.Queue()
    pending, running, codes = list(ORDER), {}, {}
    try:
        while pending or running:
            while pending and len(running) < lanes:
                s = pending.pop(0)
                p = ctx.Process(target=_child, args=(one_shape, _shape_args(args, s), out / s, inner, done_q),
                                name=f"boundary {s}")
                p.start()
                running[s] = p
            try:
                bar.update(done_q.get(timeout=0.25))
            except queue.Empty:
                pass
            for s, p in list(running.items()):
                if not p.is_alive():
                    p.join()
                    codes[s] = p.exitcode
                    del running[s]
        while True:  # what the last children reported before they ended
            try:
                bar.update(done_q.get_nowait())
            except queue.Empty:
                break
    finally:
        for p in running.values():  # Ctrl-C or an error here: no shape runs on
            p.terminate()
            p.join()
    return codes


def _child(one_shape, args, out, workers, done_q) -> None:
    os.environ[ENV_DISABLE] = "1"  # the parent's bar counts this shape's scenarios
    one_shape(args, out, workers, done_q.put)
