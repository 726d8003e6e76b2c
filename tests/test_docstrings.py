"""The public Python API documents every parameter (numpydoc: a ``Parameters`` section naming
each argument, or each field of a dataclass, and a ``Returns`` section for a function), the
way python-control checks its own (``control/tests/docstrings_test.py``): an argument added
without its line, or a line left for an argument removed, fails here."""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import re

import pytest

PUBLIC_API = (
    "soulctl.loop.run:run",
    "soulctl.loop.run:RunRequest",
    "soulctl.run_config:RunConfig",
    "soulctl.control.gains:LoopGains",
    "soulctl.control.rtc:build_rtc",
    "soulctl.control.transfer:analyze",
    "soulctl.control.mgm:MgmSettings",
    "soulctl.control.mgm:optimal_gains",
)


def _object(path: str):
    module, name = path.split(":")
    return getattr(importlib.import_module(module), name)


def _section(doc: str, title: str) -> list[str] | None:
    """The lines of a numpydoc section (``title`` underlined by dashes), None without one."""
    lines = inspect.cleandoc(doc).splitlines()
    for i, line in enumerate(lines[:-1]):
        if line.strip() == title and re.fullmatch(r"-{3,}", lines[i + 1].strip()):
            body = []
            for j in range(i + 2, len(lines)):
                if j + 1 < len(lines) and re.fullmatch(r"-{3,}", lines[j + 1].strip()):
                    break  # the next section's title
                body.append(lines[j])
            return body
    return None


def documented(doc: str | None) -> set[str] | None:
    """The names the Parameters section documents (``name : type`` lines at its margin)."""
    body = _section(doc or "", "Parameters")
    if body is None:
        return None
    names: set[str] = set()
    for line in body:
        m = re.match(r"^(\*{0,2}\w+(?:\s*,\s*\w+)*)\s*:", line)
        if m:
            names |= {n.strip().lstrip("*") for n in m.group(1).split(",")}
    return names


def parameters(obj) -> set[str]:
    if dataclasses.is_dataclass(obj):
        return {f.name for f in dataclasses.fields(obj) if f.init}
    return {p for p in inspect.signature(obj).parameters if p not in ("self", "cls")}


def missing_docs(obj) -> list[str]:
    """What the docstring of ``obj`` lacks or holds in excess; [] when complete."""
    names = documented(obj.__doc__)
    if names is None:
        return ["no Parameters section"]
    problems = [f"undocumented: {p}" for p in sorted(parameters(obj) - names)]
    problems += [f"documented but not a parameter: {p}" for p in sorted(names - parameters(obj))]
    if inspect.isfunction(obj) and _section(obj.__doc__ or "", "Returns") is None:
        problems.append("no Returns section")
    return problems


@pytest.mark.parametrize("path", PUBLIC_API)
def test_every_parameter_of_the_public_api_is_documented(path):
    assert missing_docs(_object(path)) == []


def test_the_check_finds_an_undocumented_and_a_stale_parameter():
    def f(a, b):
        """Do.

        Parameters
        ----------
        a : int
            A.
        c : int
            Gone.

        Returns
        -------
        int
        """

    assert missing_docs(f) == ["undocumented: b", "documented but not a parameter: c"]

    def g(a):
        """No sections."""

    assert missing_docs(g) == ["no Parameters section"]
