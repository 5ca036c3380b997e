"""`vitreoguard replay FILE.mcap`: re-run the safety filter on a run log and check that it
commands the same joint rates (the regression harness).

Writes replay.json ({steps, mismatches, max_abs_diff, ok, truncated, examples}) next to
the log or into --out. Exit code 0 when every step matches, 1 when one does not, 2 when
the log is missing, unreadable, corrupt or (without --allow-truncated) truncated; then
nothing is written. Replay never commands a robot.
"""
from __future__ import annotations

from pathlib import Path

from eval.cli.args import number, out_dir
from eval.cli.io import UsageError, prepare_out_dir, write_json
from eval.log.writer import LogReadError, TruncatedLogError
from eval.log.replay import replay

TOL = number(0.0, None, "rad/s")


def register(sub) -> None:
    p = sub.add_parser("replay", help="re-run the safety filter on a run log (MCAP) and compare: replay.json")
    p.add_argument("file", help="run log written by eval.log.writer.RunLogger (.mcap)")
    p.add_argument("--tol", type=TOL, default=1e-9, help=f"largest accepted |qdot difference|, {TOL.range}")
    p.add_argument("--out", type=out_dir, default=None, help="output directory (default: the log's directory)")
    p.add_argument("--allow-truncated", action="store_true",
                   help="replay a killed run's log up to its last complete step instead of refusing it")
    p.set_defaults(func=main)


def main(args) -> int:
    path = Path(args.file)
    if not path.is_file():
        raise UsageError(f"{path}: {'a folder, not a run log file' if path.is_dir() else 'no such file'}")
    try:
        result = replay(path, args.tol, args.allow_truncated)
    except TruncatedLogError as exc:
        raise UsageError(f"cannot replay: {exc}; --allow-truncated replays its complete steps") from None
    except LogReadError as exc:
        raise UsageError(f"cannot replay: {exc}") from None
    out = prepare_out_dir(args.out if args.out is not None else path.resolve().parent)
    write_json(out / "replay.json", result.as_json())
    verdict = "all match" if result.ok else f"{result.mismatches} MISMATCH(ES)"
    print(f"replay {path}: {result.steps} steps{' (truncated log)' if result.truncated else ''}, {verdict}; "
          f"max |qdot diff| {result.max_abs_diff:.3g} rad/s (tol {args.tol:g})")
    for ex in result.examples[:5]:
        print(f"  step {ex['step']} (t = {ex['t']} s): {'; '.join(ex['differences'])}")
    print(f"wrote {out / 'replay.json'}")
    return 0 if result.ok else 1
