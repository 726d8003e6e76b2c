"""The code's shape the architecture promises (docs/architecture.md): short functions, a thin
``ClosedLoop.__init__``, command modules that do not import one another."""

from __future__ import annotations

import ast
from pathlib import Path

import soulctl

PACKAGE = Path(soulctl.__file__).parent
MAX_FUNCTION_LINES = 59  # "under 60 lines", the def line to the last line, the docstring left out (numpydoc's sections are long)
MAX_CLOSED_LOOP_INIT = 44  # wiring only: one line per stage or parameter (19 parameters)


def _functions() -> list[tuple[int, str]]:
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                name = f"{path.relative_to(PACKAGE)}:{node.name} (line {node.lineno})"
                doc = node.body[0] if ast.get_docstring(node) is not None else None
                docstring = doc.end_lineno - doc.lineno + 1 if doc is not None else 0  # type: ignore[operator]
                out.append((node.end_lineno - node.lineno + 1 - docstring, name))  # type: ignore[operator]
    return out


def test_the_package_is_found():
    assert len(_functions()) > 300  # the walk sees the package, so the checks below can fail


def test_every_function_is_under_60_lines():
    long = sorted((n, name) for n, name in _functions() if n > MAX_FUNCTION_LINES)
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines: {long}"


def test_closed_loop_init_only_wires_the_stages():
    tree = ast.parse((PACKAGE / "loop" / "simulation.py").read_text())
    [cls] = [n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "ClosedLoop"]
    [init] = [n for n in cls.body if isinstance(n, ast.FunctionDef) and n.name == "__init__"]
    assert init.end_lineno - init.lineno + 1 <= MAX_CLOSED_LOOP_INIT  # type: ignore[operator]


def test_no_command_module_imports_another():
    cli = PACKAGE / "cli"
    commands = {p.stem for p in cli.glob("*.py")} - {"__init__", "app", "common", "numbers", "output", "option_table", "progress", "quick"}
    for path in cli.glob("*.py"):
        if path.stem not in commands:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 1:
                names = {node.module} if node.module else {a.name for a in node.names}
                assert not names & commands, f"cli/{path.name} imports {names & commands}"
