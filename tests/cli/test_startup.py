"""The CLI starts at once: the top level imports no command, a command imports only what it
uses (bench/bench_startup.py measures the times; here, what is imported, which does not
depend on the machine)."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile

import pytest

from soulctl.cli.app import COMMANDS, load_command

# A fresh interpreter started with ``-c`` puts its working directory first on sys.path: run it
# outside the source tree, so that it imports the installed package (with its compiled core).
OUTSIDE_THE_TREE = tempfile.gettempdir()

HEAVY = ("matplotlib", "dask", "distributed", "h5py", "astropy", "aotpy", "scipy.signal", "scipy.optimize", "scipy.stats")


def _imported_by(argv: list[str]) -> set[str]:
    """The modules a fresh interpreter holds after running soulctl with ``argv``."""
    code = (
        "import sys, json, io, contextlib\n"
        "from soulctl.cli.app import main\n"
        f"with contextlib.redirect_stdout(io.StringIO()): status = main({argv!r})\n"
        "assert status == 0, status\n"
        "print(json.dumps(sorted(sys.modules)))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=OUTSIDE_THE_TREE)
    return set(json.loads(done.stdout.strip().splitlines()[-1]))


def _heavy(modules: set[str]) -> list[str]:
    return sorted(m for m in modules if any(m == h or m.startswith(h + ".") for h in HEAVY))


@pytest.mark.parametrize("argv", [["--version"], ["--help"]])
def test_top_level_imports_no_command(argv):
    modules = _imported_by(argv)
    assert _heavy(modules) == []
    assert "numpy" not in modules
    assert not [m for m in modules if m.startswith("soulctl.cli.") and m.split(".")[2] in {c[0] for c in COMMANDS.values()}]


def test_configure_imports_no_heavy_module():
    assert _heavy(_imported_by(["configure", "--mag", "13", "--json"])) == []


def test_the_loops_help_imports_neither_its_plots_nor_scipy_signal():
    """`loop run --help` reads the option table: its plots, its telemetry writer and
    scipy.signal are imported where a run uses them.  (The run description still imports
    soulctl.loop.run and with it h5py: issue 85's downward imports.)"""
    modules = _imported_by(["loop", "run", "--help"])
    assert not {"soulctl.plots.loop", "soulctl.telemetry.hdf5", "soulctl.telemetry.stream", "scipy.signal", "matplotlib"} & modules


def test_import_of_the_cli_package_is_light():
    code = "import sys, json, soulctl.cli, soulctl.cli.app; print(json.dumps(sorted(sys.modules)))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=OUTSIDE_THE_TREE)
    assert _heavy(set(json.loads(done.stdout))) == []


def _commands():
    for name in COMMANDS:
        command = load_command(name)
        yield from (command.commands.items() if hasattr(command, "commands") else [(name, command)])


@pytest.mark.parametrize("name", list(COMMANDS))
def test_listed_summary_is_the_commands_own(name):
    """The top-level listing's summary of a command is its own help's first paragraph."""
    from rich.markup import escape

    help_text = load_command(name).help or ""
    assert escape(COMMANDS[name][2]) == " ".join(help_text.split("\n\n")[0].split())


def test_every_command_opens_with_a_one_line_summary():
    """A group lists its commands by their first paragraph: one sentence on one line each."""
    for name, command in _commands():
        first = (command.help or "").split("\n\n")[0]
        assert "\n" not in first.strip() and len(first) <= 90 and first.endswith("."), (name, first)
