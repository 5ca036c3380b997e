"""Bad paths and combinations on the command line: refused in one line (exit 2) before any
work, nothing written; and the flags that change what a command draws do change it."""
from __future__ import annotations

import json
import os

import pytest

from eval.cli import main


def run_main(capsys, *argv):
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def refused(capsys, argv, says: str):
    code, stdout, err = run_main(capsys, *argv)
    assert code == 2 and stdout == "" and err.count("\n") == 1 and says in err, err


@pytest.mark.parametrize("argv", [["eyes", "--out", ""], ["eyes", "--stl", " "], ["calibrate", "--out", ""],
                                  ["plan", "--out", ""], ["fit", "--recording", "x", "--out", ""]])
def test_an_empty_output_folder_is_refused_not_the_working_directory(argv, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    refused(capsys, argv, "must be a folder's path")
    assert os.listdir(tmp_path) == []


def test_eyes_checks_both_output_folders_before_writing_either(tmp_path, capsys):
    (tmp_path / "file").write_text("")
    refused(capsys, ["eyes", "--stl", tmp_path / "stl", "--out", tmp_path / "file" / "sub"], "not writable")
    refused(capsys, ["eyes", "--stl", tmp_path / "file", "--out", tmp_path / "png"], "not writable: it is a file")
    assert os.listdir(tmp_path) == ["file"]


def test_a_read_only_file_system_is_refused_before_any_work(tmp_path, capsys, monkeypatch):
    """os.access calls a read-only mount writable (and root may write anywhere): both checks
    probe with a file, so the first check refuses what the folder's making would; the
    probe leaves nothing behind where it succeeds."""
    import errno
    import tempfile

    real = tempfile.NamedTemporaryFile

    def read_only(*args, **kwargs):
        if str(kwargs.get("dir", "")).startswith(str(tmp_path / "ro")):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))
        return real(*args, **kwargs)

    (tmp_path / "ro").mkdir()
    monkeypatch.setattr(tempfile, "NamedTemporaryFile", read_only)
    refused(capsys, ["eyes", "--stl", tmp_path / "stl", "--out", tmp_path / "ro" / "png"], "Read-only file system")
    assert sorted(os.listdir(tmp_path)) == ["ro"] and os.listdir(tmp_path / "ro") == []
    from eval.cli.io import check_out_dir
    check_out_dir(tmp_path / "new" / "sub")
    assert sorted(os.listdir(tmp_path)) == ["ro"]


def test_eyes_draws_the_shapes_with_their_eye_params(tmp_path, capsys):
    """--eye-param reaches eyes.png and eyes.json, not only the STL phantoms: a detachment
    3 mm high lifts the retina further than the default 2 mm (the profile's peak)."""
    assert main(["eyes", "--out", str(tmp_path / "a")]) == 0
    assert main(["eyes", "--out", str(tmp_path / "b"), "--eye-param", "height_mm=3"]) == 0
    a, b = (json.loads((tmp_path / x / "eyes.json").read_text()) for x in "ab")
    assert a["detached"]["params"] == {} and b["detached"]["params"] == {"height_mm": 3.0}
    assert a["detached"]["max_inward_mm"] == pytest.approx(2.0, abs=0.05)
    assert b["detached"]["max_inward_mm"] == pytest.approx(3.0, abs=0.05)
    assert a["myopic"] == b["myopic"]


def test_plan_refuses_survey_passes_without_a_survey_before_the_scan(tmp_path, capsys, monkeypatch):
    import eval.experiments.boundary as experiments

    monkeypatch.setattr(experiments, "build_model_by_spiral", lambda *a, **k: pytest.fail("the scan ran"))
    refused(capsys, ["plan", "--out", tmp_path / "never", "--survey-passes", "3"], "--survey-passes needs --survey-mm")
    assert not (tmp_path / "never").exists()


def test_a_survey_deeper_than_the_standoffs_range_is_refused_before_the_scan(tmp_path, capsys, monkeypatch):
    import eval.experiments.boundary as experiments

    monkeypatch.setattr(experiments, "build_model_by_spiral", lambda *a, **k: pytest.fail("the scan ran"))
    refused(capsys, ["plan", "--out", tmp_path / "never", "--standoff-mm", "4.5", "--survey-mm", "0.7"],
            "--standoff-mm 4.5 + --survey-mm 0.7 puts the survey deeper than 5 mm inside the model")
    assert not (tmp_path / "never").exists()


def test_ports_less_than_an_hour_apart_are_refused_before_the_scan(tmp_path, capsys, monkeypatch):
    import eval.experiments.boundary as experiments

    monkeypatch.setattr(experiments, "build_model_by_spiral", lambda *a, **k: pytest.fail("the scan ran"))
    refused(capsys, ["plan", "--out", tmp_path / "never", "--port-clock", "superonasal=10"],
            "--port-clock: ports superonasal (10 o'clock) and superotemporal (10 o'clock) lie less than 1 clock hour")
    assert not (tmp_path / "never").exists()


@pytest.mark.parametrize("classes", ["delay,,lag", ",", "delay,"])
def test_faults_refuses_an_empty_class_name(classes, tmp_path, capsys):
    refused(capsys, ["faults", "--out", tmp_path / "never", "--classes", classes], "--classes: an empty class name")
    assert not (tmp_path / "never").exists()


def test_a_folder_where_a_file_is_due_is_named_a_folder(tmp_path, capsys):
    refused(capsys, ["replay", tmp_path], "a folder, not a run log file")
    refused(capsys, ["fit", "--recording", tmp_path, "--out", tmp_path / "never", "--ground-truth", tmp_path],
            "is a folder, not an STL file")


def test_an_unreadable_recording_is_refused_in_one_line(tmp_path, capsys, monkeypatch):
    """A recording folder the user may not list (as root every folder is readable, so the
    permission check itself is stood in for)."""
    import eval.recording.fit as fit

    rec = tmp_path / "rec"
    rec.mkdir()
    access = os.access
    monkeypatch.setattr(fit.os, "access", lambda path, mode, **kw: False if str(path) == str(rec) else access(path, mode, **kw))
    refused(capsys, ["fit", "--recording", rec, "--out", tmp_path / "never"],
            f"--recording {rec} is not readable (permission denied)")
    assert not (tmp_path / "never").exists()
