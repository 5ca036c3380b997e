"""The `vitreoguard` command line: one subcommand per experiment.

Each subcommand lives in its own module that exposes `register(subparsers)`; the
module adds its parser and sets `func(args) -> int`. A flag outside its range is refused
while parsing (eval.cli.args), other bad input raises `eval.cli.io.UsageError`: either way a
one-line message and exit code 2, before anything is written. Ctrl-C stops a run
cleanly: open logs are closed, one line says so, exit code 130.
"""
from __future__ import annotations

import importlib
import sys
from importlib.metadata import PackageNotFoundError, version

import matplotlib

matplotlib.use("Agg")  # figures are files; no display is needed or assumed

from eval.cli.args import Parser
from eval.cli.io import UsageError
from eval.interrupts import is_interrupt

SUBCOMMAND_MODULES = (
    "eval.cli.demo",
    "eval.cli.paper",
    "eval.cli.eyes",
    "eval.cli.calibrate",
    "eval.cli.replay",
    "eval.cli.scan",
    "eval.cli.boundary",
    "eval.cli.faults",
    "eval.cli.sensor",
    "eval.cli.plan",
    "eval.cli.record",
    "eval.cli.fit",
    "eval.cli.regress",
)
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as shells report it


def package_version() -> str:
    """The installed vitreoguard distribution's version ('unknown' when not installed)."""
    try:
        return version("vitreoguard")
    except PackageNotFoundError:
        return "unknown"


def build_parser() -> Parser:
    """Return the top-level parser with every subcommand registered."""
    parser = Parser(prog="vitreoguard",
                    description="Adaptive iiOCT eye model and virtual boundary. Units: mm, s, rad (deg and um where "
                                "a flag's name says so).")
    parser.add_argument("--version", action="version", version=f"%(prog)s {package_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in SUBCOMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv=None) -> int:
    """Entry point of the console script; returns the process exit code."""
    command = "vitreoguard"
    try:
        parser = build_parser()
        try:
            args = parser.parse_args(argv)
            args.argv = list(sys.argv[1:] if argv is None else argv)  # as given: what `boundary --shape all` re-runs
        except SystemExit as exc:  # --help, --version, or a refused argument (already reported)
            return exc.code if isinstance(exc.code, int) else EXIT_USAGE
        command = f"vitreoguard {args.command}"
        return int(args.func(args) or 0)
    except UsageError as exc:
        print(f"{command}: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (KeyboardInterrupt, SystemError, RuntimeError) as exc:
        if not is_interrupt(exc):  # a genuine error: its traceback
            raise
        print(f"\n{command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
