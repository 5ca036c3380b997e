"""The `vitreoguard` command line: one subcommand per experiment.

Each subcommand lives in its own module that exposes `register(subparsers)`; the
module adds its parser and sets `func(args) -> int`. Bad input raises
`eval.io.UsageError`, which becomes a one-line message and exit code 2.
"""
from __future__ import annotations

import argparse
import importlib
import sys

import matplotlib

matplotlib.use("Agg")  # figures are files; no display is needed or assumed

from eval.io import UsageError

SUBCOMMAND_MODULES = (
    "eval.cmd_demo",
    "eval.cmd_paper",
    "eval.cmd_eyes",
    "eval.cmd_calibrate",
    "eval.cmd_replay",
    "eval.cmd_scan",
    "eval.cmd_boundary",
    "eval.cmd_sensor",
    "eval.cmd_plan",
)


def build_parser() -> argparse.ArgumentParser:
    """Return the top-level parser with every subcommand registered."""
    parser = argparse.ArgumentParser(
        prog="vitreoguard",
        description="Adaptive iiOCT eye model and virtual boundary (mm, s, rad).",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in SUBCOMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv=None) -> int:
    """Entry point of the console script; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except UsageError as exc:
        print(f"vitreoguard {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
