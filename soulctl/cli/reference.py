"""The command-line reference, ``docs/cli.md``, generated from the commands' own definitions
(the help texts, option tables and defaults that ``--help`` prints), so that it cannot drift
from them: ``python -m soulctl.cli.reference > docs/cli.md``; a test fails when the file
differs from what this prints."""

from __future__ import annotations

import re
import sys

from . import app as app_module
from .app import COMMANDS, app, load_command

HEADER = """# soulctl command-line reference

Generated from the commands' definitions by `python -m soulctl.cli.reference > docs/cli.md`
(`tests/cli/test_reference.py` fails when it drifts); `soulctl COMMAND --help` prints the same.
Every command takes `--json` where it prints results, and exits with the statuses below.

| exit status | meaning |
|---|---|
"""


def exit_statuses() -> list[tuple[str, str]]:
    """(status, meaning) from the contract's one statement, the ``app`` module's docstring."""
    bullets = re.findall(r"^\* (\d+(?: / \d+)?) (.*?)(?=^\* |\Z)", app_module.__doc__ or "", re.M | re.S)
    return [(status, _cell(_plain(meaning)).rstrip(";.")) for status, meaning in bullets]


def _plain(text: str | None) -> str:
    """Help text as written: rich's escapes undone, paragraphs kept, lines joined."""
    text = (text or "").replace("\\[", "[").replace("``", "`")
    return "\n\n".join(" ".join(p.split()) for p in text.split("\n\n") if p.strip())


def _cell(text: str) -> str:
    return " ".join(text.split()).replace("|", "\\|")


def _default(param) -> str:
    match = re.search(r"\[default: (.*)\]$", _plain(param.help))
    if match:
        return match.group(1)
    if param.is_flag or param.default in (None, (), []) or param.show_default is False:
        return ""
    return str(param.default)


def _option_rows(command) -> list[str]:
    """One table per panel, in the order ``--help`` shows them."""
    panels: dict[str, list[str]] = {}
    for param in command.params:
        if getattr(param, "param_type_name", "") != "option" or param.hidden:
            continue
        names = ", ".join(f"`{o}`" for o in [*param.opts, *param.secondary_opts])
        value = "" if param.is_flag else (param.metavar or "")
        help_text = re.sub(r"\s*\[default: .*\]$", "", _plain(param.help))
        row = f"| {names} | {_cell(value)} | {_cell(_default(param))} | {_cell(help_text)} |"
        panels.setdefault(getattr(param, "rich_help_panel", None) or "Options", []).append(row)
    out = []
    for panel, rows in panels.items():
        out += [f"*{panel}*", "", "| option | value | default | what it sets |", "|---|---|---|---|", *rows, ""]
    return out


def _arguments(command) -> list[str]:
    rows = []
    for param in command.params:
        if getattr(param, "param_type_name", "") == "argument":
            name = param.metavar or param.name.upper()
            rows.append(f"- `{name}`{'' if param.required else ' (optional)'}: {_plain(getattr(param, 'help', ''))}")
    return [*rows, ""] if rows else []


def _section(path: str, command) -> list[str]:
    out = [f"## `soulctl {path}`", "", _plain(command.help), ""]
    subcommands = getattr(command, "commands", None)
    if subcommands:
        anchor = path.replace(" ", "-")
        out += [f"- [`soulctl {path} {name}`](#soulctl-{anchor}-{name}): {_plain(sub.short_help)}" for name, sub in subcommands.items()]
        out.append("")
        for name, sub in subcommands.items():
            out += _section(f"{path} {name}", sub)
        return out
    return out + _arguments(command) + _option_rows(command)


def reference() -> str:
    """The whole reference as markdown."""
    import typer

    root = typer.main.get_command(app)
    lines = [HEADER.rstrip("\n")]
    lines += [f"| {status} | {meaning} |" for status, meaning in exit_statuses()]
    options = [p for p in root.params if getattr(p, "param_type_name", "") == "option"]
    lines += ["", "Top-level options: " + ", ".join(f"`{p.opts[0]}` ({_plain(getattr(p, 'help', ''))})" for p in options), ""]
    lines += [f"- [`soulctl {name}`](#soulctl-{name}): {summary}" for name, (_, _, summary) in COMMANDS.items()]
    lines.append("")
    for name in COMMANDS:
        lines += _section(name, load_command(name))
    return "\n".join(lines).rstrip() + "\n"


if __name__ == "__main__":
    sys.stdout.write(reference())
