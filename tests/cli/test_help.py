"""Every command's --help reads well (soulctl.cli.help): no Typer type labels, plain defaults,
brackets kept as text, choices listed, and the long commands in panels."""

from __future__ import annotations

import re

import pytest

from soulctl.cli.app import COMMANDS, load_command, main


def _all_commands() -> list[list[str]]:
    out = [[]]
    for name in COMMANDS:
        command = load_command(name)
        subs = getattr(command, "commands", None)
        out += [[name, sub] for sub in subs] if subs else [[name]]
        if subs:
            out.append([name])
    return out


def _help(argv: list[str], capsys, monkeypatch, columns: int = 80) -> str:
    monkeypatch.setenv("COLUMNS", str(columns))
    monkeypatch.setenv("TERM", "dumb")
    assert main([*argv, "--help"]) == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("argv", _all_commands(), ids=lambda a: " ".join(a) or "soulctl")
def test_help_has_no_type_labels_and_plain_defaults(argv, capsys, monkeypatch):
    text = _help(argv, capsys, monkeypatch, columns=200)
    assert not re.search(r"<(bool|str|int|float|path)>", text), text
    assert "[default: (" not in text
    assert "\\[" not in text  # markup escapes never show


def test_brackets_in_help_are_text(capsys, monkeypatch):
    text = " ".join(_help(["rtc", "check"], capsys, monkeypatch, columns=200).split())
    assert "[misregistration] of --config" in text


def test_choices_are_listed(capsys, monkeypatch):
    text = _help(["loop", "run"], capsys, monkeypatch, columns=200)
    for choices in ("iir|int", "R|I|J|H|FeII|Ks"):
        assert choices in text
    assert "trial|mgm|both" in _help(["optimize", "gains"], capsys, monkeypatch, columns=200)


def test_loop_run_help_reads_in_panels(capsys, monkeypatch):
    """Grouped by what the options set, each panel short enough for a screen at 80 columns."""
    text = _help(["loop", "run"], capsys, monkeypatch)
    panels = re.findall(r"╭─ (.+?) ─", text)
    assert {"Observation", "Atmosphere and telescope", "Control", "Auxiliary loops (MGM, OGTL)", "Output"} <= set(panels)
    for body in re.split(r"╭─ .+? ─+╮\n", text)[1:]:
        assert body.count("\n") <= 40


def test_the_shared_options_are_declared_once():
    """--wind, --L0, --mag and --json have one declaration (one help text; the ranges checked
    by the parser) for every command; --seeing two: the run's and `optics gains`' correction
    level."""
    import ast
    from pathlib import Path

    import soulctl.cli

    declared: dict[str, int] = {}
    for path in Path(soulctl.cli.__file__).parent.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            callee = getattr(node.func, "attr", None) or getattr(node.func, "id", None) if isinstance(node, ast.Call) else None
            if callee in ("Option", "_turbulence_option"):
                for arg in node.args:
                    if isinstance(arg, ast.Constant) and arg.value in ("--seeing", "--wind", "--L0", "--mag", "--json"):
                        declared[arg.value] = declared.get(arg.value, 0) + 1
    assert declared == {"--seeing": 2, "--wind": 1, "--L0": 1, "--mag": 1, "--json": 1}
