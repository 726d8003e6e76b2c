"""docs/cli.md is what ``python -m soulctl.cli.reference`` prints from the commands' own
definitions: a changed option, help text or default fails here until the file is regenerated."""

from __future__ import annotations

from pathlib import Path

from soulctl.cli.app import COMMANDS
from soulctl.cli.reference import exit_statuses, reference

DOC = Path(__file__).resolve().parents[2] / "docs" / "cli.md"


def test_the_reference_is_the_commands_own():
    assert DOC.read_text() == reference(), "docs/cli.md drifted: python -m soulctl.cli.reference > docs/cli.md"


def test_the_reference_has_every_command_and_the_exit_statuses():
    text = reference()
    assert all(f"## `soulctl {name}`" in text for name in COMMANDS)
    assert "## `soulctl loop run`" in text and "`--seeing`" in text
    assert [s for s, _ in exit_statuses()] == ["0", "2", "3", "130 / 143", "141", "1"]
