"""The command line's argument types and parser class.

Each type parses one flag's text and checks its range; a bad value raises
argparse.ArgumentTypeError, which the parser reports as one line naming the flag and the
allowed range (exit code 2) while the arguments are parsed, before any output folder
exists. `Parser` prints only that line (no usage block) and shows every default in --help.
"""
from __future__ import annotations

import argparse
import math
import sys

SEED_MAX = 2**32 - 1


def _g(x) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def lo_ok(v, lo, is_open: bool) -> bool:
    return lo is None or (v > lo if is_open else v >= lo)


def hi_ok(v, hi, is_open: bool) -> bool:
    return hi is None or (v < hi if is_open else v <= hi)


class _Ranged:
    """A parser of numbers in [lo, hi] (an open end with lo_open / hi_open; None: unbounded)."""

    def __init__(self, kind, lo=None, hi=None, unit: str = "", lo_open: bool = False, hi_open: bool = False,
                 step: float | None = None):
        self.kind, self.lo, self.hi, self.unit = kind, lo, hi, unit
        self.lo_open, self.hi_open, self.step = lo_open, hi_open, step

    @property
    def range(self) -> str:
        """The allowed range as text, e.g. '[0, 500] um', '>= 1' or 'finite, mm'."""
        lo, hi = self.lo, self.hi
        if lo is None and hi is None:
            text = "finite,"
        elif hi is None:
            text = f"{'>' if self.lo_open else '>='} {_g(lo)}"
        elif lo is None:
            text = f"{'<' if self.hi_open else '<='} {_g(hi)}"
        else:
            text = f"{'(' if self.lo_open else '['}{_g(lo)}, {_g(hi)}{')' if self.hi_open else ']'}"
        text = f"{text} {self.unit}".rstrip(" ,")
        return text if self.step is None else f"{text}, whole multiples of {_g(self.step)} {self.unit}".rstrip()

    def __call__(self, text: str):
        span = self.range
        what = "an integer" if self.kind is int else "a number"
        what = f"{what} ({span})" if span.startswith("finite") else f"{what} {'' if span[0] in '<>' else 'in '}{span}"
        try:
            if "_" in text:  # Python's int() and float() read "1_0" as 10
                raise ValueError(text)
            v = self.kind(text)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}") from None
        ok = math.isfinite(v) and (self.step is None or abs(v / self.step - round(v / self.step)) <= 1e-9)
        if ok and lo_ok(v, self.lo, self.lo_open) and hi_ok(v, self.hi, self.hi_open):
            return v
        raise argparse.ArgumentTypeError(f"must be {what}, got {text}")

    def __repr__(self) -> str:  # argparse names the type in some messages
        return "integer" if self.kind is int else "number"


def integer(lo: int, hi: int | None = None, unit: str = "") -> _Ranged:
    """Type of an integer flag in [lo, hi] (hi None: no upper bound)."""
    return _Ranged(int, lo, hi, unit)


def number(lo: float | None, hi: float | None, unit: str, lo_open: bool = False, hi_open: bool = False,
           step: float | None = None) -> _Ranged:
    """Type of a finite float flag in [lo, hi] (ends open with lo_open / hi_open), a whole
    multiple of `step` when it is not None."""
    return _Ranged(float, lo, hi, unit, lo_open, hi_open, step)


SEED = integer(0, SEED_MAX)


def out_dir(text: str) -> str:
    """Type of an output folder flag (--out, --stl): a non-empty path (an empty one would
    write into the working directory)."""
    if not text.strip():
        raise argparse.ArgumentTypeError(f"must be a folder's path, got {text!r}")
    return text


out_dir.__name__ = "output folder"


def choice(name: str, options) -> callable:
    """Type of a flag that takes one of `options` (strings): 'unknown <name> ...; choose from ...'."""
    options = tuple(options)

    def parse(text: str) -> str:
        if text not in options:
            raise argparse.ArgumentTypeError(f"unknown {name} {text!r}; choose from {', '.join(options)}")
        return text

    parse.__name__ = name
    return parse


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows '(default: ...)' after every flag that has a default (not after required ones
    or those whose default is 'none')."""

    def _get_help_string(self, action):
        if action.required or action.default is None or action.default is argparse.SUPPRESS:
            return action.help
        return super()._get_help_string(action)


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line, 'prog: error: message (see prog --help)',
    exit code 2; its subparsers are of the same class and format their help alike."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")

    def parse_known_args(self, args=None, namespace=None):
        """As argparse's, with a value that reads as negative numbers joined to the long flag
        before it (`--seed -inf` as `--seed=-inf`, `--band -1,2` as `--band=-1,2`): argparse
        takes only '-1' and '-1.5' for numbers, and '-inf', '-1e3' or '-1,2' for an unknown
        flag ("expected one argument"), where the flag's own type names its range."""
        argv = list(sys.argv[1:] if args is None else args)
        out: list[str] = []
        for a in argv:
            if out and _reads_as_negative_numbers(a) and out[-1].startswith("--") and "=" not in out[-1]:
                out[-1] = f"{out[-1]}={a}"
            else:
                out.append(a)
        return super().parse_known_args(out, namespace)


def _reads_as_negative_numbers(text: str) -> bool:
    """Whether `text` starts with '-' (not '--') and each of its comma-separated parts is
    what float() reads (-1e3, -inf, -nan, -.5, -1,2)."""
    if not text.startswith("-") or text.startswith("--"):
        return False
    try:
        for part in text.split(","):
            float(part)
    except ValueError:
        return False
    return True


def eye_param(text: str) -> tuple[str, float]:
    """Type of --eye-param: 'NAME=VALUE' with a finite number VALUE (the name is checked
    against the shape later, by `eye_params`)."""
    name, sep, value = text.partition("=")
    try:
        v = float(value)
    except ValueError:
        v = math.nan
    if not sep or not name.strip() or not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be NAME=VALUE with a finite number VALUE (e.g. height_mm=3), got {text!r}")
    return name.strip(), v


eye_param.__name__ = "eye parameter"


def add_eye_param(p) -> None:
    """Add the repeatable --eye-param NAME=VALUE flag to parser `p`."""
    from models.eyes import EYE_PARAMS, param_range

    takes = "; ".join(f"{s}: " + ", ".join(f"{k} {param_range(s, k)}" for k in ps) for s, ps in EYE_PARAMS.items())
    p.add_argument("--eye-param", type=eye_param, action="append", default=[], metavar="NAME=VALUE",
                   help=f"a shape parameter of the true eye (repeatable; defaults: models.eyes.EYE_PARAMS) - {takes}")


def eye_params(pairs, shape: str) -> dict:
    """The --eye-param pairs as make_eye's keyword parameters for `shape`, checked against
    models.eyes.EYE_PARAMS and built once; raises eval.cli.io.UsageError on a name the shape
    does not take, a value out of range or a combination the builder refuses."""
    from eval.cli.io import UsageError
    from models.eyes import check_eye_params, make_eye

    def error(message: str):
        raise UsageError(message)

    params = {}
    for name, value in pairs:
        if name in params:
            error(f"--eye-param {name} given twice")
        params[name] = value
    try:
        params = check_eye_params(shape, params)
        make_eye(shape, **params)
    except ValueError as exc:
        error(f"--eye-param: {exc}")
    return params


def numbers(names: tuple, lo: float | None, hi: float | None, unit: str):
    """Type of a flag of len(names) comma-separated finite numbers, each in [lo, hi] (None:
    unbounded), e.g. 'MM,DEG'; the message names the format and the range."""
    fmt = ",".join(names)
    one = number(lo, hi, unit)

    def parse(text: str) -> tuple:
        parts = text.split(",")
        if len(parts) != len(names):
            raise argparse.ArgumentTypeError(f"must be {fmt} ({len(names)} numbers, {one.range}), got {text!r}")
        try:
            return tuple(one(p) for p in parts)
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(f"must be {fmt}, each {one.range}, got {text!r}") from None

    parse.__name__ = fmt
    parse.range = f"{fmt}, each {one.range}"
    return parse
