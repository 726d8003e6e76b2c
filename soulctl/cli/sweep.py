"""``soulctl sweep``: a grid of `loop run` cases on Dask, from a laptop to a cluster."""

from __future__ import annotations

import math
import sys
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from .. import defaults
from ..errors import InputError
from ..files import atomic_write_text
from ..observation import BINNINGS, observation_for_magnitude
from ..plots.sweep import strehl_vs_magnitude
from ..ranges import LOCAL_WORKERS_PER_CORE, WAIT_WORKERS, WAIT_WORKERS_S, Range
from ..sweep import scheduler as dask_scheduler
from ..sweep.derive import best_per_magnitude, derived_table, lut_csv
from ..sweep.estimate import CONFIRM_ABOVE_S, estimate, needs_confirmation
from ..sweep.grid import read_grid
from ..sweep.results import ResultsTable
from ..sweep.runner import execute, local_workers, plan_sweep
from . import output, progress, quick
from .common import CACHE_DIR, JSON_OUTPUT, NO_CACHE, default_cache_dir
from .numbers import number
from .option_table import command

DERIVED = "derived_lut.csv"
FIGURE = "strehl_vs_magnitude.png"
CONFIRM_TEXT = f"{CONFIRM_ABOVE_S / 3600:g} h"


def _json_row(row: dict) -> dict:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()}


def _render_derived(rows: list[dict], derived: list[dict], console: Console) -> None:
    t = Table(title="Best configuration per magnitude (highest Strehl) next to the paper's look-up table", title_justify="left")
    for col in ("R", "binning", "sub-ap.", "frame rate [Hz]", "Strehl", "paper: binning, frame rate [Hz]"):
        t.add_column(col, justify="right")
    for pick in best_per_magnitude(rows):
        paper = observation_for_magnitude(float(pick["magnitude"]))
        t.add_row(
            f"{pick['magnitude']:g}",
            str(pick["binning"]),
            str(BINNINGS[int(pick["binning"])]),
            f"{pick['frame_rate']:g}",
            f"{pick['strehl']:.3f}",
            f"{paper.binning}, {paper.frame_rate_hz:g}",
        )
    console.print(t)
    console.print("Derived look-up table (format of tables/magnitude_lut.csv):")
    print(lut_csv(derived), end="")


def _confirm(estimate_text: str) -> None:
    """Ask on the terminal before a long sweep, with the estimate; InputError unless the
    answer is yes."""
    err = output.console(stderr=True)
    err.print(f"{estimate_text}. This sweep takes more than {CONFIRM_TEXT} of CPU. Start it? [y/N] ", end="")
    try:
        answer = sys.stdin.readline()
    except (OSError, ValueError):
        answer = ""
    if not answer.endswith("\n"):  # end of input: the terminal echoed no line end
        err.print()
    if answer.strip().lower() not in ("y", "yes"):
        raise InputError("sweep not started (not confirmed; --yes starts a long sweep without asking); nothing was run")


@dataclass(frozen=True)
class SweepOptions:
    """The options of `sweep` (an option table: see ``option_table``)."""

    grid: Path = typer.Argument(
        ...,
        metavar="GRID.toml",
        help="The grid: loop run parameters (magnitude, seeing, wind, L0, duration, binning, frame_rate, tt_control, "
        "gain_method, band, seed, noise, vibrations, resonance, oversampling, wfs_field); a list is an axis.",
    )
    scheduler: str | None = typer.Option(
        None,
        "--scheduler",
        metavar="ADDRESS",
        help=f"An existing Dask scheduler, tcp://HOST:PORT (only tcp://; it must answer within "
        f"{dask_scheduler.CONNECT_TIMEOUT_S:g} s; default: a local cluster).",
    )
    workers: int | None = typer.Option(
        None,
        "--workers",
        parser=number(Range(1, 2**31, integer=True)),
        help=f"Processes of the local cluster (1..{LOCAL_WORKERS_PER_CORE} per core; default: one per core).",
    )
    out: Path = typer.Option(
        Path("sweep"),
        "--out",
        metavar="DIR",
        help="Folder of results.csv (and the figures, the derived table); created once everything else is checked.",
    )
    resume: bool = typer.Option(
        False, "--resume", help="Complete an interrupted sweep: keep the finished rows of DIR/results.csv (checked line by line)."
    )
    plot: bool = typer.Option(False, "--plot", help=f"Write DIR/{FIGURE}.")
    derive_table: bool = typer.Option(
        False, "--derive-table", help=f"Print (and write DIR/{DERIVED}) the best binning and rate per magnitude."
    )
    yes: bool = typer.Option(
        False, "--yes", "-y", help=f"Start without asking when the estimate exceeds {CONFIRM_TEXT} of CPU (asked on a terminal only)."
    )
    wait_workers: float = typer.Option(
        WAIT_WORKERS_S,
        "--wait-workers",
        metavar="S",
        parser=number(WAIT_WORKERS),
        help=f"With --scheduler: how long to wait for its first worker ({WAIT_WORKERS.text()}).",
    )
    no_cache: bool = NO_CACHE
    cache_dir: Path | None = CACHE_DIR
    json_output: bool = JSON_OUTPUT


@command(SweepOptions)
def sweep(o: SweepOptions) -> int:
    """Run a grid of simulated closed loops as Dask tasks, one row per case.

    The rows (parameters, Strehl, jitter, residual, run time, seed, version) go to
    DIR/results.csv, appended case by case and put in the grid's order once every case has its row.  A failed or
    diverged case is a row with its reason; --resume completes an interrupted sweep without
    recomputing its finished rows.  Each distinct calibration is computed once and shared.
    The estimated cost is printed first; above an hour of CPU a terminal is asked to confirm
    (--yes skips the question).  One sweep at a time per folder.  Exit status 0 once every
    case has a row, whatever its status; 2 (nothing run, nothing created) for a bad grid, an
    option, an unreachable scheduler or a results file that cannot be resumed.

    Example: soulctl sweep grid.toml --workers 2 --out sweep/ --plot --derive-table
    """
    cases = read_grid(o.grid)
    if quick.active():
        cases = [quick.sweep_case(c, defaults.DURATION_S) for c in cases]
        field, longest = f"{quick.FIELD_ARCSEC:g}", f"{quick.SWEEP_DURATION_S:g}"
        quick.notice(f"the pyramid's field {field}\" unless the grid gives one, cases of at most {longest} s")
    _check_cluster(o.scheduler, o.workers, o.wait_workers)
    outputs = [name for name, wanted in ((DERIVED, o.derive_table), (FIGURE, o.plot)) if wanted]
    plan = plan_sweep(cases, o.out, o.resume, outputs)
    if o.scheduler is not None and plan.todo:
        dask_scheduler.probe(o.scheduler)
    cost = estimate([c for _, c in plan.todo], None if o.scheduler else o.workers or local_workers())
    asked = needs_confirmation(cost) and not o.yes and sys.stdin.isatty()
    if asked:  # a dialogue on the terminal: the estimate and the question
        _confirm(cost.text())
    cache = None if o.no_cache else str(o.cache_dir or default_cache_dir())
    report = _execute_with_progress(plan, cost, asked, o.scheduler, o.workers, cache, o.wait_workers, o.json_output)
    assert report.results is not None  # execute() always writes its results
    rows = list(ResultsTable.read_rows(report.results).values())
    derived = derived_table(rows) if o.derive_table else None
    if derived is not None:
        atomic_write_text(o.out / DERIVED, lut_csv(derived))
    if o.plot:
        strehl_vs_magnitude(rows, o.out / FIGURE)
    if o.json_output:
        output.print_json(_json_report(report, cost, derived))
    else:
        _render_report(report, rows, derived)
    return 0


def _check_cluster(scheduler: str | None, workers: int | None, wait_workers: float) -> None:
    """--scheduler, --workers and --wait-workers: each in its range, not --workers with --scheduler."""
    if workers is not None:
        Range(1, LOCAL_WORKERS_PER_CORE * local_workers(), integer=True).check(
            workers, f"--workers ({LOCAL_WORKERS_PER_CORE} per core at most)"
        )
    if scheduler is not None and workers is not None:
        raise InputError("--workers sizes the local cluster; with --scheduler the scheduler's workers run the cases")
    if scheduler is not None:
        dask_scheduler.parse_address(scheduler)
    WAIT_WORKERS.check(wait_workers, "--wait-workers")


def _execute_with_progress(plan, cost, asked: bool, scheduler, workers, cache, wait_workers: float, json_output: bool):
    """``execute`` with its progress on stderr (``cli.progress``: a bar on a terminal, lines
    with ``soulctl --progress``); the estimate printed once the run starts."""
    how = progress.mode()
    if how == "lines":
        return _execute_with_lines(plan, cost, scheduler, workers, cache, wait_workers, json_output)
    show = how == "live"
    bar = Progress(
        TextColumn("sweep"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("cases"),
        TextColumn("{task.fields[state]}"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=output.console(stderr=True),
        transient=True,
    )
    with bar if show else nullcontext():
        task = bar.add_task("sweep", total=None, state="") if show else None

        def started(n):
            # The estimate once the run really starts (the scheduler answered, the folder is
            # locked): a refusal before it stays one line on stderr and nothing on stdout.
            if not json_output and not asked:
                output.console(stderr=True).print(cost.text())
            if show:
                assert task is not None
                bar.update(task, total=n, state=f"running {min(n, workers or n)}")

        def finished(row, report):
            if show:
                assert task is not None
                left = bar.tasks[0].total - report.computed
                bar.update(task, completed=report.computed, state=f"failed {report.failed}, diverged {report.diverged}, running {left}")

        report = execute(plan, scheduler, workers, cache, on_row=finished, on_start=started, wait_workers_s=wait_workers)
    return report


def _execute_with_lines(plan, cost, scheduler, workers, cache, wait_workers: float, json_output: bool):
    """``execute`` with ``soulctl --progress`` into a log: the estimate, then lines of cases."""
    with progress.counted("sweep", "cases", before="starting the workers") as tick:
        assert tick is not None

        def started(n):
            if not json_output:
                output.console(stderr=True).print(cost.text())
            tick(0, n)

        def finished(row, report):
            tick(report.computed)

        return execute(plan, scheduler, workers, cache, on_row=finished, on_start=started, wait_workers_s=wait_workers)


def _json_report(report, cost, derived) -> dict:
    return {
        "total": report.total,
        "skipped": report.skipped,
        "computed": report.computed,
        "failed": report.failed,
        "diverged": report.diverged,
        "results": str(report.results),
        "estimate": cost.as_json(),
        "notes": report.notes,
        "rows": [_json_row(r) for r in report.rows],
        "derived_table": derived,
    }


def _render_report(report, rows: list[dict], derived) -> None:
    console = output.console()
    for note in report.notes:
        console.print(f"note: {note}")
    console.print(
        f"{report.total} cases: {report.computed} run now ({report.failed} failed, {report.diverged} diverged), "
        f"{report.skipped} kept from an earlier run; results in {report.results}"
    )
    for r in report.rows:
        if r["status"] != "ok":
            console.print(f"  case {r['case_id']} {r['status']}: {r['reason']}")
    if derived is not None:
        _render_derived(rows, derived, console)
