"""Progress on stderr: one rule for every step that takes more than ~2 s (the pyramid's
calibration, a loop's frames, a filter design per rate, an identification, a sweep's cases).

- stderr a terminal: a live bar or spinner, removed when the step ends, with or without
  ``--json`` (the JSON is on stdout; stderr is the person's);
- stderr not a terminal (a log file, a pipe, CI): nothing, so that a script's stderr holds only
  errors and warnings, unless ``soulctl --progress ...``, which writes plain lines instead: one
  when a step starts, then every ``LINE_EVERY`` of its frames or cases, and one when it ends.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar

from .output import console as make_console

# `soulctl --progress`: set by the root option for the one command it runs (app.py resets it)
REQUESTED: ContextVar[bool] = ContextVar("soulctl_progress", default=False)
LINE_EVERY = 0.1  # with --progress into a log: a line per tenth of a step's frames or cases
PREPARING = "calibrating the pyramid (the first time; cached after) and building the loop"

Tick = Callable[..., None]  # tick(done, total=None): what `run`, `optimize` and a sweep call


def mode() -> str | None:
    """'live' (stderr is a terminal), 'lines' (``soulctl --progress`` into a log) or None."""
    if sys.stderr.isatty():
        return "live"
    return "lines" if REQUESTED.get() else None


def _line(text: str) -> None:
    print(f"soulctl: {text}", file=sys.stderr, flush=True)


@contextmanager
def step(label: str) -> Iterator[None]:
    """A step without a count (a design, an identification): a spinner, or two lines."""
    how = mode()
    if how == "live":
        with make_console(stderr=True).status(label + "…"):
            yield
    elif how == "lines":
        start = time.perf_counter()
        _line(label + "…")
        yield
        _line(f"{label}: done in {time.perf_counter() - start:.1f} s")
    else:
        yield


@contextmanager
def counted(label: str, unit: str, total: int | None = None, before: str = PREPARING) -> Iterator[Tick | None]:
    """A step over ``total`` frames or cases: a bar labelled ``before`` until the first tick
    (first-time work, such as the calibration, comes before it), or lines; yields its
    ``tick(done, total=None)``, or None when nothing is shown."""
    how = mode()
    if how == "live":
        with _bar(label, unit, total, before) as tick:
            yield tick
    elif how == "lines":
        start = time.perf_counter()
        yield _lines(label, unit, total, before)
        _line(f"{label}: done in {time.perf_counter() - start:.1f} s")
    else:
        yield None


@contextmanager
def _bar(label: str, unit: str, total: int | None, before: str) -> Iterator[Tick]:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn(unit))
    with Progress(*columns, TimeElapsedColumn(), TimeRemainingColumn(), console=make_console(stderr=True), transient=True) as bar:
        task = bar.add_task(before, total=total)

        def tick(done: int, total: int | None = None) -> None:
            bar.update(task, completed=done, total=total, description=label)  # rich keeps the total when None

        yield tick


def _lines(label: str, unit: str, total: int | None, before: str) -> Tick:
    _line(before + "…")
    known, due = total, 0

    def tick(done: int, total: int | None = None) -> None:
        nonlocal known, due
        known = total or known
        if done < due:
            return
        _line(f"{label}: {done}/{known} {unit}" if known else f"{label}: {done} {unit}")
        due = done + (max(1, round(LINE_EVERY * known)) if known else 1)

    return tick
