"""eval.cli.progress: bars and phase spinners on a terminal's stderr, whole lines elsewhere."""
from __future__ import annotations

import io
import threading
import time

import pytest

from eval.cli import progress
from eval.cli.progress import ENV_DISABLE, phase, progress_bar


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


@pytest.fixture
def shown(monkeypatch):
    """Progress on (the suite turns it off in conftest)."""
    monkeypatch.delenv(ENV_DISABLE, raising=False)


def test_a_bar_counts_on_a_terminal_and_clears_its_line(shown, capsys):
    term = Terminal()
    with progress_bar(3, "scenarios", unit="scenario", stream=term) as bar:
        for _ in range(3):
            bar.update()
            bar.refresh()
    text = term.getvalue()
    assert "scenarios" in text and "3/3" in text and "scenario/s" in text
    assert text.endswith("\r")  # the line is cleared at the end (leave=False)
    assert capsys.readouterr() == ("", "")  # neither stdout nor the real stderr


@pytest.mark.parametrize("total, stream, env", [(1, Terminal(), None), (10, io.StringIO(), None), (10, Terminal(), "1")])
def test_a_bar_shows_nothing_when_tiny_off_a_terminal_or_turned_off(total, stream, env, monkeypatch):
    monkeypatch.delenv(ENV_DISABLE, raising=False)
    if env is not None:
        monkeypatch.setenv(ENV_DISABLE, env)
    bar = progress_bar(total, "x", stream=stream)
    bar.update()
    bar.update(n=2)
    bar.close()
    bar.close()  # idempotent
    assert stream.getvalue() == ""


def test_the_suite_runs_with_progress_turned_off():
    assert not progress.enabled(Terminal())


def test_a_short_phase_shows_nothing(shown):
    term = Terminal()
    with phase("quick", stream=term, delay_s=0.5):
        pass
    assert term.getvalue() == ""


def test_a_long_phase_shows_a_spinner_with_the_elapsed_time_and_clears_it(shown, capsys):
    term, threads = Terminal(), threading.active_count()
    with phase("compiling", stream=term, delay_s=0.1):
        time.sleep(0.1 + 3 * progress.PHASE_REFRESH_S)
    text = term.getvalue()
    frames = [f for f in text.split("\r") if f.strip()]
    assert len(frames) >= 2 and all("compiling 00:0" in f for f in frames)
    assert {f[0] for f in frames} <= set(progress.SPINNER) and len({f[0] for f in frames}) >= 2  # it turns
    assert text.endswith("\r") and text.split("\r")[-2].strip() == ""  # cleared
    assert threading.active_count() == threads
    assert capsys.readouterr() == ("", "")


def test_a_phase_ended_by_an_exception_still_clears_its_line(shown):
    term, threads = Terminal(), threading.active_count()
    with pytest.raises(KeyboardInterrupt):
        with phase("planning", stream=term, delay_s=0.05):
            time.sleep(0.3)
            raise KeyboardInterrupt
    assert "planning" in term.getvalue() and term.getvalue().split("\r")[-2].strip() == ""
    assert threading.active_count() == threads


def test_phases_are_off_when_turned_off():
    term = Terminal()
    with phase("compiling", stream=term, delay_s=0.0):
        time.sleep(0.3)
    assert term.getvalue() == ""


def test_off_a_terminal_a_bar_writes_whole_lines_at_most_every_interval(shown, monkeypatch, capsys):
    log = io.StringIO()
    monkeypatch.setattr(progress, "LINE_INTERVAL_S", 0.0)
    with progress_bar(4, "scenarios", unit="scenario", stream=log) as bar:
        bar.update()
        bar.update(n=3)
    lines = log.getvalue().splitlines()
    assert "\r" not in log.getvalue() and len(lines) == 3  # two updates and the close
    assert lines[0].startswith("scenarios: 1/4 scenario (25 %), ") and lines[-1].startswith("scenarios: 4/4 scenario (100 %)")
    monkeypatch.setattr(progress, "LINE_INTERVAL_S", 3600.0)
    quiet = io.StringIO()
    with progress_bar(4, "scenarios", stream=quiet) as bar:  # done within the interval: no line at all
        bar.update(n=4)
    assert quiet.getvalue() == "" and capsys.readouterr() == ("", "")


def test_off_a_terminal_a_long_phase_writes_a_line_and_its_duration(shown):
    log, threads = io.StringIO(), threading.active_count()
    with phase("compiling", stream=log, delay_s=0.05):
        time.sleep(0.3)
    assert log.getvalue().splitlines() == ["compiling ...", "compiling: 0 s"]
    short = io.StringIO()
    with phase("quick", stream=short, delay_s=0.5):
        pass
    assert short.getvalue() == ""
    assert threading.active_count() == threads
