"""Commands declared as an option table: Typer sees the table's options, the body gets them."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import typer
from typer.testing import CliRunner

from soulctl.cli.option_table import command


@dataclass(frozen=True)
class _Options:
    name: str = typer.Argument(..., help="A name.")
    count: int = typer.Option(2, "--count", help="How many.")
    out: Path | None = typer.Option(None, "--out")
    loud: bool = typer.Option(False, "--loud/--quiet")


def _app(seen: list) -> typer.Typer:
    app = typer.Typer()

    @app.command()
    @command(_Options)
    def greet(o: _Options) -> int:
        """Greet NAME."""
        seen.append(o)
        return 0

    @app.command()
    def other() -> None:  # two commands: Typer keeps the command names
        pass

    return app


def test_the_body_gets_the_parsed_options():
    seen: list = []
    result = CliRunner().invoke(_app(seen), ["greet", "vega", "--count", "5", "--out", "x.txt", "--loud"])
    assert result.exit_code == 0, result.output
    assert seen == [_Options(name="vega", count=5, out=Path("x.txt"), loud=True)]


def test_defaults_help_and_bad_values_come_from_the_table():
    seen: list = []
    app = _app(seen)
    assert CliRunner().invoke(app, ["greet", "vega"]).exit_code == 0
    assert seen == [_Options(name="vega", count=2, out=None, loud=False)]
    help_text = CliRunner().invoke(app, ["greet", "--help"]).output
    assert "Greet NAME." in help_text and "--count" in help_text and "How many." in help_text
    bad = CliRunner().invoke(app, ["greet", "vega", "--count", "many"])
    assert bad.exit_code == 2 and not seen[1:]
