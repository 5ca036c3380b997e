"""`python -m eval.experiments.results_report`: run the tools and write the results tables (docs/results.md).

Runs `vitreoguard boundary` on every shape (N adversarial scenarios, N/10 in the sphere
phase, seed 11; `--jobs` of them at a time, each in its own process), `vitreoguard plan`
and `vitreoguard sensor` on the emmetropic eye and, with `--paper`, `vitreoguard paper
--seeds 1`; each writes its JSON under `--out`. The tables are made from that JSON
alone: every table says the command that produced it, the date and the package
version. `--no-run` rewrites the tables from the JSON of an earlier run in `--out`.

Exit codes: 0 written, 1 a tool failed (its log is in OUT/logs; the tables are left as
they were), 2 bad flags (one line), 130 interrupted (Ctrl-C).
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from eval.cli.io import UsageError, prepare_out_dir, write_atomic, write_json
from models.eyes import EYE_SHAPES
from models.scan.spiral import PAPER_PITCH_MM, PAPER_REVOLUTIONS

ROOT = Path(__file__).resolve().parents[2]  # the checkout whose tools are run
SEED = 11
PLAN_SHAPE = SENSOR_SHAPE = "emmetropic"
SKIPPABLE = ("boundary", "plan", "sensor")

# formats: name -> (scale applied to the JSON value, decimals); "int", "str" and "bool" print as they are
# (a missing value prints "n/a"; in a "when" column, whose None means "never", it prints "none")
FORMATS = {"int": (1, 0), "f1": (1, 1), "f3": (1, 3), "f5": (1, 5), "pct": (100, 1), "pct2": (100, 2),
           "when": (100, 1), "um_of_mm": (1000, 1), "str": None, "bool": None}

# tables: (title, the job(s) they read, explanation, [(column header with unit, JSON path, format)])
BOUNDARY_SAFETY = [
    ("shape", "shape", "str"), ("scenarios", "scenarios", "int"),
    ("violations (scenarios < 0.45 mm)", "violations", "int"), ("contacts (scenarios <= 0 mm)", "contacts", "int"),
    ("min true clearance (mm)", "min_true_clearance_mm", "f3"), ("lens violations (scenarios)", "lens_violations", "int"),
    ("failsafe stops (count)", "failsafe_stops", "int"), ("intervention (% of steps)", "intervention_fraction", "pct"),
    ("free tracking RMSE (mm/s)", "tracking_rmse_mm_s", "f5"), ("max RCM error (um)", "max_rcm_error_um", "f1"),
]
BOUNDARY_MODEL = [
    ("shape", "shape", "str"), ("model the filter used", "model.kind", "str"), ("MAE (um)", "model.mae_um", "f1"),
    ("scanned p95 (um)", "model.scanned_p95_um", "f1"), ("3-sigma coverage", "model.sigma3_coverage", "f3"),
    ("3-sigma coverage, lowest during the scan", "model.on_the_way.lowest_sigma3_coverage", "f3"),
    ("transition (% of spiral)", "model.transition_at", "when"), ("EF MAE (um)", "model.ef_mae_um", "f1"),
    ("SF MAE (um)", "model.sf_mae_um", "f1"), ("model points", "model.n_points", "int"),
    ("spiral min true clearance (mm)", "spiral.min_true_clearance_mm", "f3"),
    ("sphere phase: scenarios", "sphere_phase.scenarios", "int"),
    ("sphere phase: violations (scenarios)", "sphere_phase.violations", "int"),
    ("sphere phase: contacts (scenarios)", "sphere_phase.contacts", "int"),
    ("sphere phase: min true clearance (mm)", "sphere_phase.min_true_clearance_mm", "f3"),
    ("sphere phase: model's 3-sigma coverage", "sphere_phase.model.sigma3_coverage", "f3"),
    ("sphere phase: model's unsafe-side misses (%)", "sphere_phase.model.sigma3_unsafe_fraction", "pct2"),
]
BOUNDARY_SPEED = [
    ("shape", "shape", "str"), ("filter step median (us)", "solve_us.median", "int"),
    ("filter step p99 (us)", "solve_us.p99", "int"), ("Drake diff. IK median (us)", "drake_diffik_us.median", "int"),
    ("Drake diff. IK p99 (us)", "drake_diffik_us.p99", "int"), ("realtime factor (x)", "realtime_factor", "f1"),
    ("realtime factor, unlogged scenarios (x)", "realtime_factor_unlogged", "f1"),
]
PLAN_PATH = [
    ("shape", "shape", "str"), ("model", "model_kind", "str"),
    ("band coverage (% of all band cells)", "band_coverage", "pct"),
    ("planned cells swept (%)", "planned_cells_swept", "pct"), ("port switches", "port_switches", "int"),
    ("re-entries", "reentries", "int"),
    ("min model clearance (mm)", "min_model_clearance_mm", "f3"), ("min true clearance (mm)", "min_true_clearance_mm", "f3"),
    ("violations (steps)", "violations", "int"), ("duration (s)", "duration_s", "f1"),
    ("min joint margin (deg)", "min_joint_margin_deg", "f1"),
    ("filter intervention (% of steps)", "filter_intervention_fraction", "pct2"),
    ("failsafe stops (count)", "execution.failsafe_stops", "int"), ("plan time (s)", "plan_time_s", "f1"),
]
PLAN_BAND = [
    ("shape", "shape", "str"), ("band cells", "cells", "int"), ("planned (cells)", "planned_cells", "int"),
    ("superonasal (cells)", "ports.superonasal.cells_assigned", "int"),
    ("superotemporal (cells)", "ports.superotemporal.cells_assigned", "int"),
    ("shaft (cells)", "unreachable.shaft", "int"), ("reach (cells)", "unreachable.reach", "int"),
    ("lens (cells)", "unreachable.lens", "int"), ("port (cells)", "unreachable.port", "int"),
    ("scleral depression (cells)", "unreachable.depression", "int"), ("declined (cells)", "unreachable.declined", "int"),
]
SENSOR = [
    ("shape", "shape", "str"), ("mode", "mode", "str"), ("samples", "n_samples", "int"),
    ("invalid (% of samples)", "invalid_fraction", "pct"), ("distance bias (um)", "distance_bias_um", "f1"),
    ("distance SD (um)", "distance_sd_um", "f1"), ("distance error p99 (um)", "distance_error_p99_um", "f1"),
    ("outliers rejected (points)", "outliers_rejected", "int"), ("model points", "n_points", "int"),
    ("EF MAE (um)", "ef_mae_um", "f1"), ("SF MAE (um)", "sf_mae_um", "f1"), ("final model", "kind_final", "str"),
    ("model the filter used", "model.kind", "str"), ("its MAE (um)", "model.mae_um", "f1"),
    ("its 3-sigma coverage", "model.sigma3_coverage", "f3"),
]
PAPER = [
    ("shape", "shape", "str"), ("EF MAE exact (um)", "ef_mae.0", "um_of_mm"), ("SF MAE exact (um)", "sf_mae.0", "um_of_mm"),
    ("EF MAE sampled (um)", "ef_mae_sampled.0", "um_of_mm"), ("paper's EF MAE (um)", "paper.ef_mae.0", "um_of_mm"),
    ("transition (% of spiral)", "transition_at", "when"),
    ("optimal transition (% of spiral)", "optimal_transition_at", "when"), ("lag (% of spiral)", "lag", "pct"), ("right", "decision_right", "bool"), ("timely", "timely", "bool"),
]

TABLES = [
    ("Virtual boundary: safety", "boundary", f"Each row: the model built by the paper's spiral ({PAPER_REVOLUTIONS:g} "
     f"turns, {PAPER_PITCH_MM:g} mm pitch) through the closed loop, then adversarial scenarios of 0.5 s. Clearances "
     "are TRUE clearances (ground-truth retina) of the tip, port and shaft points; a violation is a scenario whose "
     "smallest true clearance is below 0.45 mm (the 0.5 mm boundary, 50 um tolerance), a contact one at or below 0.",
     BOUNDARY_SAFETY),
    ("Virtual boundary: model and sphere phase", "boundary", "The model the filter used at the end of the spiral "
     "(local, ellipsoid or sphere; exact MAE against the true retina over the paper's reference region, scanned p95 "
     "within 10 deg of a measured direction, 3-sigma coverage of the true retina at the end and, lowest, during the "
     "scan; README: boundary.json), the global fits' MAE, and the campaign against the model of the spiral's first "
     "quarter of its turns, with that model's 3-sigma coverage and the share of the reference samples beyond 3 sigma "
     "on the side the barrier relies on (the model's retina beyond the true one).", BOUNDARY_MODEL),
    ("Virtual boundary: speed", "boundary", "The filter's whole compiled step against Drake's "
     "DoDifferentialInverseKinematics on every 10th step's state of the same runs; realtime factor = simulated time / "
     "wall time of the simulations (the first scenario, logged step by step for replay, included; then without it).",
     BOUNDARY_SPEED),
    ("Peripheral vitrectomy plan: path and execution", "plan", "Band coverage: the share of ALL band cells (equator to "
     "ora serrata, 360 deg, 1 mm cells) whose shaving target the executed cutter port passed within half a sweep width, "
     "through the two working ports on the true eye; planned cells swept: the same share of the cells the plan "
     "assigned to a port; violations: control steps whose true clearance is below 0.45 mm.", PLAN_PATH),
    ("Peripheral vitrectomy plan: band", "plan", "The band's cells: how many each working port sweeps, and why the "
     "others are not reached (shaft: the shaft would graze the retina; scleral depression: reachable only with the "
     "wall indented; declined: reached, but too few for a pass of their own).", PLAN_BAND),
    ("iiOCT sensor chain", "sensor", "The spiral through robot, simulated iiOCT (full A-scans) and adaptive model; "
     "distance errors against the true distance (median, robust SD, p99 of |error|).", SENSOR),
    ("Paper reproduction (1 seed)", "paper", "The paper's simulation (Table 2, Fig. 5) with the predictive transition "
     "criterion; MAE exact and in the paper's sampled form; transitions as fractions of the spiral.", PAPER),
]


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, exit 2
        self.exit(2, f"{self.prog}: error: {message}\n")


def _bounded_int(lo: int, hi: int):
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer in [{lo}, {hi}], got {text!r}") from None
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"expected an integer in [{lo}, {hi}], got {v}")
        return v
    return parse


def parse_args(argv=None) -> argparse.Namespace:
    p = _Parser(prog="python -m eval.experiments.results_report", description="Run the tools (boundary on every shape, plan, sensor, optionally paper) and write the "
                            "results tables from their JSON.")
    p.add_argument("--out", default="out/results", help="folder for the tools' outputs and logs (default: %(default)s)")
    p.add_argument("--doc", default=str(ROOT / "docs" / "results.md"),
                   help="the Markdown file to write (default: docs/results.md of this checkout)")
    p.add_argument("--scenarios", type=_bounded_int(1, 100_000), default=1000,
                   help="adversarial scenarios per shape; the sphere phase gets N // 10 (default: %(default)s)")
    p.add_argument("--shapes", nargs="+", choices=EYE_SHAPES, default=list(EYE_SHAPES), metavar="SHAPE",
                   help=f"shapes for `boundary` (default: all: {' '.join(EYE_SHAPES)})")
    p.add_argument("--paper", action="store_true", help="also run `vitreoguard paper --seeds 1`")
    p.add_argument("--skip", nargs="+", choices=SKIPPABLE, default=[], metavar="TOOL",
                   help=f"tools not to run, of: {' '.join(SKIPPABLE)}")
    p.add_argument("--jobs", type=_bounded_int(1, 64), default=2, help="tools run at a time (default: %(default)s)")
    p.add_argument("--no-run", action="store_true", help="only rewrite the tables from the JSON already in --out")
    return p.parse_args(argv)


def plan_jobs(args) -> dict:
    """name -> (tool arguments after `vitreoguard`, output folder, JSON file) of every run."""
    out, jobs = Path(args.out), {}
    if "boundary" not in args.skip:
        sphere = args.scenarios // 10
        for shape in args.shapes:
            d = out / "boundary" / shape
            jobs[f"boundary-{shape}"] = (["boundary", "--shape", shape, "--scenarios", str(args.scenarios),
                                          "--sphere-scenarios", str(sphere), "--seed", str(SEED), "--jobs", "1", "--out", str(d)],
                                         d, d / "boundary.json")
    if "plan" not in args.skip:
        d = out / "plan"
        jobs["plan"] = (["plan", "--shape", PLAN_SHAPE, "--out", str(d)], d, d / "plan.json")
    if "sensor" not in args.skip:
        d = out / "sensor"
        jobs["sensor"] = (["sensor", "--shape", SENSOR_SHAPE, "--out", str(d)], d, d / "sensor.json")
    if args.paper:
        d = out / "paper"
        jobs["paper"] = (["paper", "--seeds", "1", "--jobs", str(args.jobs), "--out", str(d)], d, d / "table2.json")
    return jobs


def package_version() -> str:
    try:
        import tomllib

        return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    except Exception:  # noqa: BLE001 - Python 3.10 or no pyproject: the installed metadata
        from importlib.metadata import PackageNotFoundError, version

        try:
            return version("vitreoguard")
        except PackageNotFoundError:
            return "unknown"


def git_commit() -> str | None:
    try:
        r = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                           timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() or None if r.returncode == 0 else None


def run_job(name: str, tool_args: list, log_dir: Path) -> dict:
    """Run `vitreoguard <tool_args>` of this checkout; its output goes to log_dir/<name>.log."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    started = dt.datetime.now().astimezone()
    t0 = time.perf_counter()
    with open(log_dir / f"{name}.log", "w") as log:
        code = subprocess.run([sys.executable, "-m", "eval.cli", *tool_args], cwd=ROOT, env=env, stdout=log,
                              stderr=subprocess.STDOUT).returncode
    wall = time.perf_counter() - t0
    print(f"  {name}: {'done' if code == 0 else f'FAILED (exit {code})'} in {wall:.0f} s", flush=True)
    return {"command": "vitreoguard " + " ".join(tool_args), "started": started.isoformat(timespec="seconds"),
            "wall_s": wall, "exit": code}


def run_all(args, jobs: dict, out: Path, report: str) -> tuple[dict, list]:
    """Run the jobs (`--jobs` at a time; the paper last, with its own worker processes): (the
    manifest OUT/runs.json: this `report` command and every run, the names of the runs that failed)."""
    logs = prepare_out_dir(out / "logs")
    for _, d, _ in jobs.values():
        prepare_out_dir(d)
    version, commit = package_version(), git_commit()
    print(f"running {len(jobs)} tool run(s), {args.jobs} at a time; logs in {logs}", flush=True)
    parallel = [n for n in jobs if n != "paper"]
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        done = dict(zip(parallel, pool.map(lambda n: run_job(n, jobs[n][0], logs), parallel)))
    if "paper" in jobs:
        done["paper"] = run_job("paper", jobs["paper"][0], logs)
    for entry in done.values():
        entry.update(version=version, commit=commit)
    manifest_path = out / "runs.json"
    old = json.loads(manifest_path.read_text()).get("runs", {}) if manifest_path.is_file() else {}
    manifest = {"report": report, "runs": {**old, **done}}  # a partial run (--skip) keeps the others' entries
    write_json(manifest_path, manifest)
    return manifest, [n for n, e in done.items() if e["exit"] != 0]


def value_at(data, path: str):
    """data["a"]["b"][0] for path "a.b.0" (None where a part is missing)."""
    for part in path.split("."):
        if data is None:
            return None
        data = data[int(part)] if isinstance(data, list) else data.get(part)
    return data


def format_cell(value, fmt: str) -> str:
    if value is None:
        return "none" if fmt == "when" else "n/a"
    if fmt == "str":
        return str(value)
    if fmt == "bool":
        return "yes" if value else "no"
    scale, decimals = FORMATS[fmt]
    return f"{round(value * scale):d}" if decimals == 0 else f"{value * scale:.{decimals}f}"


def table_lines(columns: list, rows: list[dict]) -> list[str]:
    lines = ["| " + " | ".join(c[0] for c in columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        lines.append("| " + " | ".join(format_cell(value_at(row, path), fmt) for _, path, fmt in columns) + " |")
    return lines


def load_results(out: Path, manifest: dict) -> dict:
    """tool -> [(run entry of the manifest, its JSON rows)] for every run that left JSON."""
    found: dict = {}
    for name, entry in manifest["runs"].items():
        if entry.get("exit") != 0:
            continue
        tool = name.split("-", 1)[0]
        if tool == "boundary":
            data = json.loads((out / "boundary" / name.split("-", 1)[1] / "boundary.json").read_text())
            rows = [data]
        elif tool == "paper":
            data = json.loads((out / "paper" / "table2.json").read_text())
            rows = [{"shape": shape, **r} for shape, r in data.items()]
        else:
            rows = [json.loads((out / tool / f"{tool}.json").read_text())]
        found.setdefault(tool, []).append((entry, rows))
    if "boundary" in found:  # the shapes in their usual order
        found["boundary"].sort(key=lambda e: EYE_SHAPES.index(e[1][0]["shape"]))
    return found


def _command_line(entries: list) -> str:
    """The command(s) of a table's runs: one, or a pattern over the shapes."""
    commands = [e["command"] for e, _ in entries]
    if len(commands) > 1:
        shapes = [rows[0]["shape"] for _, rows in entries]
        template = commands[0].replace(f"--shape {shapes[0]}", "--shape SHAPE").replace(f"/{shapes[0]}", "/SHAPE")
        return f"`{template}` for SHAPE in {', '.join(shapes)}"
    return f"`{commands[0]}`"


def markdown(found: dict, command: str) -> str:
    lines = ["# Results", "",
             f"Written by `{command}` (`make results`) from the JSON the tools wrote; do not edit by hand. "
             "What each figure means: README.md, *Evaluate a virtual boundary* and *Plan a peripheral vitrectomy*.", ""]
    for title, tool, explanation, columns in TABLES:
        entries = found.get(tool)
        if not entries:
            continue
        first = entries[0][0]
        dates = sorted({e["started"][:10] for e, _ in entries})
        date = dates[0] if len(dates) == 1 else f"{dates[0]} to {dates[-1]}"
        commit = f", commit {first['commit']}" if first.get("commit") else ""
        lines += [f"## {title}", "",
                  f"{_command_line(entries)}; {date}; "
                  f"vitreoguard {first['version']}{commit}.", "", explanation, ""]
        lines += table_lines(columns, [row for _, rows in entries for row in rows]) + [""]
    runs = [e for entries in found.values() for e, _ in entries]
    if runs:
        lines += ["## Runs", "", "| command | started | wall time (s) |", "|---|---|---|"]
        lines += [f"| `{e['command']}` | {e['started']} | {e['wall_s']:.0f} |" for e in runs] + [""]
    return "\n".join(lines)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_args(argv)
    try:
        if args.no_run:
            out = Path(args.out)
            if not (out / "runs.json").is_file():
                raise UsageError(f"--no-run: {out / 'runs.json'} not found (run without --no-run first)")
            manifest = json.loads((out / "runs.json").read_text())
        else:
            out = prepare_out_dir(args.out)
            report = " ".join(["python -m eval.experiments.results_report", *argv])
            manifest, failed = run_all(args, plan_jobs(args), out, report)
            if failed:
                print(f"results_report: error: {', '.join(failed)} failed; see {out / 'logs'}; "
                      f"{args.doc} left as it was", file=sys.stderr)
                return 1
        doc = Path(args.doc)
        prepare_out_dir(doc.parent)
        write_atomic(doc, markdown(load_results(out, manifest), manifest["report"]))
    except UsageError as exc:
        print(f"python -m eval.experiments.results_report: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # the tools' processes get the same Ctrl-C and stop too
        print("\npython -m eval.experiments.results_report: interrupted", file=sys.stderr)
        return 130
    print(f"wrote {doc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
