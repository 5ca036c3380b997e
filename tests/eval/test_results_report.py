"""`python -m eval.experiments.results_report`: the tables hold the numbers of the tools' own JSON, each
table says the command, date and version that produced it, and bad flags exit 2 on one line."""
from __future__ import annotations

import datetime as dt
import json
import subprocess
import sys

import pytest

from eval.experiments import results_report as rr


def tables(markdown: str) -> dict:
    """section title -> (the line under the title, [row dicts: column header -> cell text])."""
    out, title, header, first = {}, None, None, None
    for line in markdown.splitlines():
        if line.startswith("## "):
            title, header, first = line[3:], None, None
            out[title] = (None, [])
        elif title and first is None and line.strip():
            first = line
            out[title] = (first, [])
        elif title and line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if header is None:
                header = cells
            elif not set(line) <= set("|-"):
                out[title][1].append(dict(zip(header, cells)))
    return out


def agrees(cell: str, value, fmt: str) -> bool:
    """The cell shows `value` at the table's precision."""
    if value is None:
        return cell == ("none" if fmt == "when" else "n/a")
    if fmt == "str":
        return cell == str(value)
    if fmt == "bool":
        return cell == ("yes" if value else "no")
    scale, decimals = rr.FORMATS[fmt]
    return abs(float(cell) - value * scale) <= 0.5 * 10.0**-decimals + 1e-9 * abs(value * scale)


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("results")
    out, doc = tmp / "out", tmp / "results.md"
    code = rr.main(["--out", str(out), "--doc", str(doc), "--scenarios", "2", "--shapes", "emmetropic"])
    return code, out, doc


@pytest.mark.slow
def test_the_tables_hold_the_json_numbers(report):
    code, out, doc = report
    assert code == 0
    found = tables(doc.read_text())
    boundary = json.loads((out / "boundary" / "emmetropic" / "boundary.json").read_text())
    plan = json.loads((out / "plan" / "plan.json").read_text())
    sensor = json.loads((out / "sensor" / "sensor.json").read_text())
    # the figures a reader looks for first, by their column names
    safety = found["Virtual boundary: safety"][1][0]
    assert safety["shape"] == "emmetropic" and safety["scenarios"] == "2"
    assert safety["violations (scenarios < 0.45 mm)"] == str(boundary["violations"])
    assert safety["contacts (scenarios <= 0 mm)"] == str(boundary["contacts"])
    assert abs(float(safety["min true clearance (mm)"]) - boundary["min_true_clearance_mm"]) <= 5e-4
    speed = found["Virtual boundary: speed"][1][0]
    assert abs(float(speed["filter step p99 (us)"]) - boundary["solve_us"]["p99"]) <= 0.5
    assert abs(float(speed["Drake diff. IK p99 (us)"]) - boundary["drake_diffik_us"]["p99"]) <= 0.5
    path = found["Peripheral vitrectomy plan: path and execution"][1][0]
    assert abs(float(path["band coverage (% of all band cells)"]) - 100 * plan["band_coverage"]) <= 0.05
    assert abs(float(path["min true clearance (mm)"]) - plan["min_true_clearance_mm"]) <= 5e-4
    chain = found["iiOCT sensor chain"][1][0]
    assert abs(float(chain["distance bias (um)"]) - sensor["distance_bias_um"]) <= 0.05
    # and every cell of every table
    data = {"boundary": boundary, "plan": plan, "sensor": sensor}
    for title, tool, _, columns in rr.TABLES:
        if tool == "paper":
            assert title not in found  # not asked for
            continue
        (line, rows) = found[title]
        assert len(rows) == 1
        for header, path, fmt in columns:
            assert agrees(rows[0][header], rr.value_at(data[tool], path), fmt), (title, header)


@pytest.mark.slow
def test_each_table_names_its_command_date_and_version(report):
    _, out, doc = report
    found = tables(doc.read_text())
    today = dt.date.today().isoformat()
    version = rr.package_version()
    commands = {"Virtual boundary: safety": "`vitreoguard boundary --shape emmetropic --scenarios 2 --sphere-scenarios 0 "
                                            "--seed 11 --jobs 1 --out", "Peripheral vitrectomy plan: band": "`vitreoguard plan "
                "--shape emmetropic", "iiOCT sensor chain": "`vitreoguard sensor --shape emmetropic"}
    for title, command in commands.items():
        line = found[title][0]
        assert line.startswith(command), line
        assert today in line and f"vitreoguard {version}" in line, line


@pytest.mark.slow
def test_no_run_rewrites_the_same_tables(report, tmp_path):
    _, out, doc = report
    again = tmp_path / "again.md"
    assert rr.main(["--out", str(out), "--doc", str(again), "--no-run"]) == 0
    assert tables(again.read_text()) == tables(doc.read_text())


@pytest.mark.parametrize("argv, message", [
    (["--scenarios", "0"], "--scenarios"),
    (["--shapes", "round"], "--shapes"),
    (["--skip", "everything"], "--skip"),
    (["--jobs", "two"], "--jobs"),
    (["--bogus"], "unrecognized"),
])
def test_bad_flags_exit_2_with_one_line(argv, message, tmp_path):
    doc = tmp_path / "results.md"
    r = subprocess.run([sys.executable, "-m", "eval.experiments.results_report", "--out", str(tmp_path / "out"), "--doc", str(doc),
                        *argv], capture_output=True, text=True, cwd=rr.ROOT, timeout=120)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0] and "error" in lines[0]
    assert not doc.exists() and not (tmp_path / "out").exists()


def test_no_run_without_a_previous_run_exits_2(tmp_path, capsys):
    assert rr.main(["--out", str(tmp_path / "out"), "--doc", str(tmp_path / "r.md"), "--no-run"]) == 2
    assert "runs.json" in capsys.readouterr().err
    assert not (tmp_path / "r.md").exists()
