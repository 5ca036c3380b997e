"""`vitreoguard regress`: the committed golden cases pass; a changed figure is a
regression (exit 1) named in the table; an unreadable golden set is exit 2 with one line."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from eval.cli import main
from eval.experiments.regress import Case, compare, figures

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden"


def _run(capsys, *argv):
    code = main(["regress", *map(str, argv)])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.slow
def test_the_committed_golden_cases_pass(capsys):
    code, out, err = _run(capsys, GOLDEN)
    assert code == 0, out + err
    assert "boundary-emmetropic:" in out and "all pass" in out and "REGRESSION" not in out


@pytest.fixture
def calibrate_case(tmp_path):
    shutil.copytree(GOLDEN / "calibrate", tmp_path / "golden" / "calibrate")
    return tmp_path / "golden"


def test_a_changed_figure_is_a_regression_named_in_the_table(calibrate_case, capsys):
    path = calibrate_case / "calibrate" / "expected" / "calibration.json"
    d = json.loads(path.read_text())
    key = next(k for k, v in d.items() if isinstance(v, float))
    d[key] = d[key] * (1 + 1e-6) + 1e-6  # beyond the default 1e-9 tolerance
    path.write_text(json.dumps(d))
    code, out, _ = _run(capsys, calibrate_case)
    assert code == 1
    assert any(line.split()[:2] == ["calibrate", key] and line.endswith("REGRESSION") for line in out.splitlines()), out


def test_update_stores_what_the_run_wrote(calibrate_case, capsys):
    shutil.rmtree(calibrate_case / "calibrate" / "expected")
    assert _run(capsys, calibrate_case)[0] == 2  # nothing to compare with yet
    assert _run(capsys, calibrate_case, "--update")[0] == 0
    assert _run(capsys, calibrate_case)[0] == 0


@pytest.mark.parametrize("spec, message", [
    ("{not json", "not JSON"),
    ('["boundary"]', "must be a JSON object"),
    ('{"command": "boundary", "args": []}', "lacks ['summary']"),
    ('{"command": "boundary", "args": [], "summary": "b.json", "colour": 1}', "unknown keys ['colour']"),
    ('{"command": "regress", "args": [], "summary": "b.json"}', "command must be one of"),
    ('{"command": "boundary", "args": ["--out", "x"], "summary": "b.json"}', "without --out"),
    ('{"command": "boundary", "args": [3], "summary": "b.json"}', "list of strings"),
    ('{"command": "boundary", "args": [], "summary": "../b.json"}', "file name"),
    ('{"command": "boundary", "args": [], "summary": "b.json", "tolerance": {"abs": -1}}', "finite number >= 0"),
    ('{"command": "boundary", "args": [], "summary": "b.json", "tolerances": {"x": {"relative": 1}}}', "'abs' and/or 'rel'"),
])
def test_a_malformed_spec_is_one_line_and_exit_2(tmp_path, capsys, spec, message):
    (tmp_path / "case").mkdir()
    (tmp_path / "case" / "spec.json").write_text(spec)
    code, out, err = _run(capsys, tmp_path)
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and message in err and "spec.json" in err, err
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["case", "spec.json"]  # nothing written


def test_a_missing_or_empty_golden_directory_is_exit_2(tmp_path, capsys):
    assert _run(capsys, tmp_path / "none")[0] == 2
    code, _, err = _run(capsys, tmp_path)
    assert code == 2 and "holds no case" in err


def _case(**kw) -> Case:
    base = dict(name="c", folder=Path("."), command="boundary", args=(), summary="s.json", log=None,
                tolerance={"abs": 1e-9, "rel": 0.0}, tolerances={}, ignore=())
    return Case(**(base | kw))


def test_figures_are_compared_within_their_stated_tolerance():
    case = _case(tolerances={"a.x": {"abs": 0.1, "rel": 0.0}}, ignore=("skip*",))
    rows = {r.figure: r.ok for r in compare(case, {"a": {"x": 1.0, "y": 2.0}, "k": "sphere", "skip_me": 1,
                                                   "realtime_factor": 9.0, "l": [1, 2]},
                                            {"a": {"x": 1.05, "y": 2.0 + 2e-9}, "k": "sphere", "skip_me": 5,
                                             "realtime_factor": 1.0, "l": [1, 3], "new": True})}
    assert rows == {"a.x": True, "a.y": False, "k": True, "l.0": True, "l.1": False, "new": False}
    assert figures({"a": [{"b": 1}], "c": None}) == {"a.0.b": 1, "c": None}
