"""Progress on stderr (``soulctl/cli/progress.py``): a bar on a terminal, nothing into a log,
plain lines into a log with ``soulctl --progress``."""

from __future__ import annotations

import json
import subprocess

import pytest

from soulctl.cli import progress


def test_into_a_log_nothing_is_shown_and_no_callback_is_made(capsys):
    with progress.counted("closed loop", "frames", total=10) as tick:
        assert tick is None
    with progress.step("designing"):
        pass
    assert capsys.readouterr().err == ""


def test_a_terminal_bar_takes_both_callback_forms(monkeypatch):
    # `run` reports frames done; `optimize` frames done and the total it now expects
    monkeypatch.setattr(progress, "mode", lambda: "live")
    with progress.counted("closed loop", "frames", total=10) as tick:
        assert tick is not None
        tick(3)
        tick(5, 20)


def test_lines_say_the_first_time_work_then_every_tenth_then_the_end(monkeypatch, capsys):
    monkeypatch.setattr(progress, "mode", lambda: "lines")
    with progress.counted("closed loop", "frames", total=100) as tick:
        assert tick is not None
        for done in range(1, 101):
            tick(done)
    lines = capsys.readouterr().err.splitlines()
    assert lines[0] == f"soulctl: {progress.PREPARING}…"
    assert lines[1:4] == [f"soulctl: closed loop: {n}/100 frames" for n in (1, 11, 21)]
    assert len(lines) == 12 and lines[-1].startswith("soulctl: closed loop: done in ")


@pytest.mark.slow
def test_soulctl_progress_writes_lines_into_a_log_also_with_json(tmp_path):
    """`soulctl --progress ... --json` into a log: the JSON alone on stdout, progress lines on
    stderr (the designs per rate); without --progress stderr stays empty."""
    argv = ["filter", "design", "--rate", "1700", "--json", "--seed", "2"]
    quiet = subprocess.run(["soulctl", *argv], capture_output=True, text=True, timeout=300, check=True)
    assert quiet.stderr == ""
    logged = subprocess.run(["soulctl", "--progress", *argv], capture_output=True, text=True, timeout=300, check=True)
    assert json.loads(logged.stdout)["designs"][0]["iir"] == json.loads(quiet.stdout)["designs"][0]["iir"]
    assert logged.stderr.splitlines()[0] == "soulctl: designing the 1700 Hz filter (1 of 1, ~5 s each)…"
    assert "done in" in logged.stderr.splitlines()[1]
