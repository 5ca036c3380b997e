"""`vitreoguard boundary --shape all`: the boundary campaign on all six eyes in one command.

Each shape runs as `vitreoguard boundary` of the same arguments, their `--shape` and `--out`
replaced by `--shape S --out OUT/S`, in a fresh process, one after the other, its
scenarios on all the workers (--jobs, or Ray); it writes what `boundary --shape S` writes
and shows its own progress. OUT/summary.json holds every shape's headline figures and the
wall time. Measured on 2 cores (6 x 1,000 scenarios): 160 s this way. Slower, measured:
every shape in one process, 202 s (the earlier shapes' loops and results stay in the heap
the workers fork and the collector scans); each shape in a process forked from this one,
242 s, and two shapes at a time (--jobs 1 each), 240 s: their simulations ran 20-25 %
slower than in a fresh process's forked workers.
"""
from __future__ import annotations

import json
import subprocess
import sys
import time

from eval.cli.io import UsageError, prepare_out_dir, write_json
from models.eyes import EYE_SHAPES

ALL = "all"
HEADLINE = ("scenarios", "violations", "contacts", "min_true_clearance_mm", "failsafe_stops", "realtime_factor")


def without(argv: list, flags: tuple) -> list:
    """argv with every occurrence of the long options `flags` and their values removed
    (`--flag VALUE`, `--flag=VALUE`, or an abbreviation argparse accepted: it accepts only
    a prefix that names one option)."""
    out, skip = [], False
    for token in argv:
        if skip:
            skip = False
            continue
        name = token.split("=", 1)[0]
        if len(name) > 2 and name.startswith("--") and any(f.startswith(name) for f in flags):
            skip = "=" not in token
            continue
        out.append(token)
    return out


def run_all(args) -> int:
    """Run `boundary` on every shape (module docstring); prints a table and writes
    OUT/summary.json. Returns the exit code: 0, or the first failed shape's."""
    if args.eye_param:
        raise UsageError("--eye-param needs one --shape (the parameters are a shape's), not --shape all")
    out = prepare_out_dir(args.out)
    t0, codes = time.perf_counter(), {}
    for k, shape in enumerate(EYE_SHAPES, start=1):
        print(f"[{k}/{len(EYE_SHAPES)}] {shape}", file=sys.stderr, flush=True)
        argv = [sys.executable, "-m", "eval.cli", *without(args.argv, ("--shape", "--out")), "--shape", shape,
                "--out", str(out / shape)]
        codes[shape] = subprocess.run(argv, stdout=subprocess.DEVNULL).returncode
        if codes[shape] != 0:
            print(f"boundary --shape {shape} failed (exit {codes[shape]}): see its output above", file=sys.stderr)
            return codes[shape]
    wall = time.perf_counter() - t0
    rows = {s: {k: json.loads((out / s / "boundary.json").read_text()).get(k) for k in HEADLINE} for s in EYE_SHAPES}
    write_json(out / "summary.json", {"shapes": rows, "wall_s": wall, "argv": args.argv})
    print(f"{'shape':12s} {'scenarios':>9s} {'violations':>10s} {'contacts':>8s} {'min true clearance (mm)':>24s}")
    for s, r in rows.items():
        print(f"{s:12s} {r['scenarios']:9d} {r['violations']:10d} {r['contacts']:8d} {r['min_true_clearance_mm']:24.4f}")
    print(f"all shapes in {wall:.1f} s wall; wrote {out / 'summary.json'} and one folder per shape")
    return 0
