"""Golden simulation cases: re-run a command, replay its log, compare its summary figures
with the ones kept from a known-good version.

A golden directory holds one folder per case, each with `spec.json`:

    {"command": "boundary", "args": ["--scenarios", "3", ...],   # a vitreoguard command, without --out
     "summary": "boundary.json",                                 # the JSON it writes
     "log": "boundary.mcap",                                     # the MCAP log it writes, or null
     "tolerance": {"abs": 1e-9, "rel": 1e-9},                    # optional: |got - expected| <= abs + rel |expected|
     "tolerances": {"min_true_clearance_mm": {"abs": 1e-12}},    # optional, per figure (dotted keys)
     "ignore": ["model.outliers_rejected"]}                      # optional, fnmatch patterns of figures not compared

and `expected/` with the summary and the log of the known-good run. Figures are the
summary's numbers, strings and booleans, nested keys joined by dots, list items by their
index. Figures of wall time (IGNORED_ALWAYS) and the log paths are never compared; the
others must agree within the tolerance (numbers) or exactly. The new log must replay
(the filter's own consistency) and the expected log must replay on the current code (the
filter decides as the known-good one did on the same inputs).
"""
from __future__ import annotations

import contextlib
import fnmatch
import io
import json
import math
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from eval.log.reader import LogReadError
from eval.log.replay import replay

DEFAULT_TOLERANCE = {"abs": 1e-9, "rel": 1e-9}  # a deterministic simulation: the same within rounding
# wall-time figures differ from run to run; log paths name the run's folder
IGNORED_ALWAYS = ("*realtime_factor*", "*solve_us*", "*drake_diffik_us*", "*filter_replay_us*", "*wall_s*", "*_time_s", "logs", "logs.*")
SPEC_KEYS = {"command", "args", "summary", "log", "tolerance", "tolerances", "ignore"}


class SpecError(ValueError):
    """A golden case that cannot be read: the message names the file and what is wrong."""


@dataclass(frozen=True)
class Case:
    name: str
    folder: Path
    command: str
    args: tuple
    summary: str
    log: str | None
    tolerance: dict
    tolerances: dict
    ignore: tuple

    def tolerance_of(self, key: str) -> dict:
        return self.tolerances.get(key, self.tolerance)

    def ignored(self, key: str) -> bool:
        return any(fnmatch.fnmatchcase(key, p) for p in IGNORED_ALWAYS + self.ignore)


@dataclass
class Row:
    """One compared figure (or a replay / run check): expected, got, tolerance, passed."""

    case: str
    figure: str
    expected: object
    got: object
    tolerance: str
    ok: bool


@dataclass
class CaseResult:
    case: Case
    rows: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return all(r.ok for r in self.rows)


def _tolerance(d, where: str) -> dict:
    if not isinstance(d, dict) or set(d) - {"abs", "rel"} or not d:
        raise SpecError(f"{where} must be an object with 'abs' and/or 'rel', got {json.dumps(d)[:60]}")
    out = {"abs": 0.0, "rel": 0.0}
    for k, v in d.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v >= 0):
            raise SpecError(f"{where}.{k} must be a finite number >= 0, got {v!r}")
        out[k] = float(v)
    return out


def _file_name(v, where: str, optional: bool = False) -> str | None:
    if v is None and optional:
        return None
    if not isinstance(v, str) or not v or "/" in v or "\\" in v or v in (".", ".."):
        raise SpecError(f"{where} must be a file name (no folders){' or null' if optional else ''}, got {v!r}")
    return v


def load_case(folder: Path, commands) -> Case:
    """The case in `folder` (its spec.json); SpecError saying what is wrong. `commands`: the allowed command names."""
    path = folder / "spec.json"
    try:
        spec = json.loads(path.read_text())
    except OSError as exc:
        raise SpecError(f"{path}: cannot read it: {exc.strerror or exc}") from None
    except ValueError as exc:
        raise SpecError(f"{path}: not JSON: {exc}") from None
    if not isinstance(spec, dict):
        raise SpecError(f"{path}: must be a JSON object, got {type(spec).__name__}")
    unknown, missing = set(spec) - SPEC_KEYS, {"command", "args", "summary"} - set(spec)
    if unknown or missing:
        raise SpecError(f"{path}: " + (f"unknown keys {sorted(unknown)}" if unknown else f"lacks {sorted(missing)}"))
    if spec["command"] not in commands:
        raise SpecError(f"{path}: command must be one of {', '.join(sorted(commands))}, got {spec['command']!r}")
    args = spec["args"]
    if not isinstance(args, list) or not all(isinstance(a, str) for a in args) or "--out" in args:
        raise SpecError(f"{path}: args must be a list of strings without --out (regress chooses the folder)")
    tolerances = spec.get("tolerances", {})
    ignore = spec.get("ignore", [])
    if not isinstance(tolerances, dict):
        raise SpecError(f"{path}: tolerances must be an object of figure -> {{abs, rel}}")
    if not isinstance(ignore, list) or not all(isinstance(p, str) for p in ignore):
        raise SpecError(f"{path}: ignore must be a list of figure patterns (strings)")
    return Case(folder.name, folder, spec["command"], tuple(args), _file_name(spec["summary"], f"{path}: summary"),
                _file_name(spec.get("log"), f"{path}: log", optional=True),
                _tolerance(spec.get("tolerance", DEFAULT_TOLERANCE), f"{path}: tolerance"),
                {str(k): _tolerance(v, f"{path}: tolerances.{k}") for k, v in tolerances.items()}, tuple(ignore))


def load_cases(golden: Path, commands) -> list[Case]:
    """Every case folder (holding spec.json) of `golden`, by name; SpecError when there is none or one is unreadable."""
    if not golden.is_dir():
        raise SpecError(f"{golden}: not a directory of golden cases")
    folders = sorted(p for p in golden.iterdir() if (p / "spec.json").exists())
    if not folders:
        raise SpecError(f"{golden}: holds no case (a folder with spec.json)")
    return [load_case(f, commands) for f in folders]


def figures(d, prefix: str = "") -> dict:
    """{dotted key: value} of the scalars of nested dicts and lists."""
    if isinstance(d, dict):
        return {k: v for key, val in d.items() for k, v in figures(val, f"{prefix}{key}.").items()}
    if isinstance(d, list):
        return {k: v for i, val in enumerate(d) for k, v in figures(val, f"{prefix}{i}.").items()}
    return {prefix[:-1]: d}


def _number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def compare(case: Case, expected: dict, got: dict) -> list[Row]:
    """A Row per figure of either summary (ignored ones left out)."""
    e, g = figures(expected), figures(got)
    rows = []
    for key in sorted(set(e) | set(g)):
        if case.ignored(key):
            continue
        a, b = e.get(key, "(absent)"), g.get(key, "(absent)")
        if _number(a) and _number(b):
            tol = case.tolerance_of(key)
            ok = (math.isnan(a) and math.isnan(b)) or abs(b - a) <= tol["abs"] + tol["rel"] * abs(a)
            rows.append(Row(case.name, key, a, b, f"{tol['abs']:g} + {tol['rel']:g} rel", bool(ok)))
        else:
            rows.append(Row(case.name, key, a, b, "equal", a == b))
    return rows


def _replay_row(case: Case, what: str, path: Path) -> Row:
    try:
        r = replay(path)
        return Row(case.name, f"replay of the {what} log", "0 mismatches", f"{r.mismatches} of {r.steps} steps",
                   "equal", r.ok)
    except LogReadError as exc:
        return Row(case.name, f"replay of the {what} log", "readable", str(exc)[:80], "equal", False)


def run_case(case: Case, run_command, update: bool = False) -> CaseResult:
    """Re-run `case` with run_command(argv) -> exit code (its stdout swallowed), compare,
    replay; with `update`, store its summary and log as the expected ones instead.
    SpecError when the expected files are missing (and not updating)."""
    expected_dir = case.folder / "expected"
    names = [case.summary] + ([case.log] if case.log else [])
    if not update:
        for name in names:
            if not (expected_dir / name).is_file():
                raise SpecError(f"{expected_dir / name}: missing (create it with --update)")
    result = CaseResult(case)
    with tempfile.TemporaryDirectory(prefix=f"regress-{case.name}-") as tmp:
        out = Path(tmp) / "out"
        with contextlib.redirect_stdout(io.StringIO()):
            code = run_command([case.command, *case.args, "--out", str(out)])
        result.rows.append(Row(case.name, "exit code", 0, code, "equal", code == 0))
        if code != 0 or not (out / case.summary).is_file():
            return result
        if update:
            expected_dir.mkdir(exist_ok=True)
            for name in names:
                shutil.copyfile(out / name, expected_dir / name)
            result.rows.append(Row(case.name, "expected files", "", "updated", "", True))
            return result
        try:
            expected = json.loads((expected_dir / case.summary).read_text())
        except ValueError as exc:
            raise SpecError(f"{expected_dir / case.summary}: not JSON: {exc}") from None
        result.rows += compare(case, expected, json.loads((out / case.summary).read_text()))
        if case.log:
            result.rows.append(_replay_row(case, "new", out / case.log))
            result.rows.append(_replay_row(case, "expected", expected_dir / case.log))
    return result


def table(results: list[CaseResult], all_rows: bool = False) -> str:
    """The comparison as a text table: every failing row (all rows with all_rows), then one line per case."""
    def cell(v) -> str:
        return f"{v:.10g}" if isinstance(v, float) else str(v)

    rows = [r for res in results for r in res.rows if all_rows or not r.ok]
    head = ("case", "figure", "expected", "got", "tolerance", "")
    body = [(r.case, r.figure, cell(r.expected), cell(r.got), r.tolerance, "ok" if r.ok else "REGRESSION") for r in rows]
    width = [max(len(x[i]) for x in [head, *body]) for i in range(len(head))]
    lines = ["  ".join(x[i].ljust(width[i]) for i in range(len(head))).rstrip() for x in [head, *body]] if body else []
    for res in results:
        failed = sum(not r.ok for r in res.rows)
        lines.append(f"{res.case.name}: {len(res.rows)} checks, " + ("all pass" if not failed else f"{failed} REGRESSED"))
    return "\n".join(lines)
