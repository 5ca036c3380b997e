"""`vitreoguard regress GOLDEN_DIR [--update]`: re-run each golden case (eval.experiments.regress),
replay its log, compare every summary figure with the known-good one within the case's
stated tolerance, print a table. Exit code 0: every case passes; 1: a regression; 2: the
golden directory or a case's spec is unreadable (nothing run)."""
from __future__ import annotations

from pathlib import Path

from eval.cli.io import UsageError
from eval.cli.progress import progress_bar

EXIT_REGRESSION = 1


def register(sub) -> None:
    p = sub.add_parser("regress", help="re-run golden cases, replay their logs, compare their figures: a table")
    p.add_argument("golden", metavar="GOLDEN_DIR", help="folder of cases: <case>/spec.json and <case>/expected/")
    p.add_argument("--update", action="store_true", help="re-run and store the results as the expected ones")
    p.add_argument("--all", action="store_true", help="list every compared figure, not only the failing ones")
    p.set_defaults(func=main)


def main(args) -> int:
    from eval import cli
    from eval.experiments.regress import SpecError, load_cases, run_case, table

    commands = {name.rsplit(".", 1)[1] for name in cli.SUBCOMMAND_MODULES} - {"regress"}
    try:
        cases = load_cases(Path(args.golden), commands)
    except SpecError as exc:
        raise UsageError(str(exc)) from None
    results = []
    with progress_bar(len(cases), "golden cases", unit="case") as bar:
        for case in cases:
            try:
                results.append(run_case(case, cli.main, update=args.update))
            except SpecError as exc:
                raise UsageError(str(exc)) from None
            bar.update()
    print(table(results, all_rows=args.all))
    return 0 if all(r.ok for r in results) else EXIT_REGRESSION
