"""Imports only run down: every import of a soulctl module by another (at the top of a module or
inside a function alike) goes to the same or a lower layer of ``LAYERS``, and no modules import
each other in a circle (docs/architecture.md, "Layers")."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "soulctl"

# Bottom to top.  A unit is a module or a subpackage of soulctl; within one, modules import
# each other freely (but not in circles).
LAYERS: tuple[tuple[str, ...], ...] = (
    ("soulctl", "soulctl._core", "soulctl.errors", "soulctl.blas"),  # the package, its compiled core, the errors
    ("soulctl.files", "soulctl.ranges"),  # reading and writing files; accepted ranges
    ("soulctl.tables",),  # the paper's tables, with their provenance
    ("soulctl.defaults",),  # a run's defaults
    ("soulctl.optics",),  # pupil, atmosphere, pyramid, mirror, calibration
    ("soulctl.disturbance",),  # turbulence and vibration PSDs
    ("soulctl.control",),  # filters, transfer functions, RTC, gains, MGM, OGTL
    ("soulctl.observation",),  # the observation: star, frame rate, modes, Tip/Tilt controller
    ("soulctl.telemetry",),  # telemetry formats and their analysis
    ("soulctl.loop",),  # the simulated loop and the live optimisers
    ("soulctl.run_config",),  # the run description: TOML <-> the loop's request
    ("soulctl.offline",),  # what a record gives: its loop, offline MGM
    ("soulctl.identify",),  # the plant identified from a record
    ("soulctl.sweep",),  # grids of runs
    ("soulctl.plots",),  # figures
    ("soulctl.cli",),  # the command line
)


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The soulctl modules ``name`` imports, wherever in the file."""
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([node.module] if node.module else []))
            for alias in node.names:
                full = f"{base}.{alias.name}"
                found.add(full if full in modules else base)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
    return {m for m in found if m.split(".")[0] == "soulctl" and m != name}


def _unit(module: str) -> str:
    parts = module.split(".")
    return ".".join(parts[:2])


def _layer(module: str) -> int:
    unit = _unit(module)
    for i, members in enumerate(LAYERS):
        if unit in members:
            return i
    raise AssertionError(f"{module} belongs to no layer: add its unit to LAYERS")


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def test_every_import_runs_down_or_within_its_unit():
    upward = [f"{a} -> {b}" for a, targets in _graph().items() for b in sorted(targets) if _unit(a) != _unit(b) and _layer(b) > _layer(a)]
    assert upward == []


def test_no_modules_import_each_other_in_a_circle():
    graph = _graph()
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    circles = []

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                circles.append(" -> ".join(path[path.index(nxt) :] + [node, nxt]) if nxt in path else f"{node} -> {nxt}")
            elif nxt not in state:
                visit(nxt, [*path, node])
        state[node] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [])
    assert circles == []


def test_the_check_finds_an_upward_import_and_a_circle(tmp_path, monkeypatch):
    """The checks can fail: an optics module importing the CLI, and two modules importing each
    other, are both reported."""
    fake = tmp_path / "soulctl"
    (fake / "optics").mkdir(parents=True)
    (fake / "cli").mkdir()
    for name in ("__init__.py", "optics/__init__.py", "cli/__init__.py"):
        (fake / name).write_text("")
    (fake / "optics" / "a.py").write_text("from ..cli import b\n")
    (fake / "cli" / "b.py").write_text("def f():\n    from ..optics import a\n")
    monkeypatch.setitem(globals(), "PACKAGE", fake)
    graph = _graph()
    assert graph["soulctl.optics.a"] == {"soulctl.cli.b"} and graph["soulctl.cli.b"] == {"soulctl.optics.a"}
    try:
        test_every_import_runs_down_or_within_its_unit()
    except AssertionError as e:
        assert "soulctl.optics.a -> soulctl.cli.b" in str(e)
    else:
        raise AssertionError("the upward import was not found")
    try:
        test_no_modules_import_each_other_in_a_circle()
    except AssertionError as e:
        assert "soulctl.cli.b" in str(e) and "soulctl.optics.a" in str(e)
    else:
        raise AssertionError("the circle was not found")
