"""``soulctl sweep``: a grid of `loop run` cases on Dask, from a laptop to a cluster."""

from __future__ import annotations

import json
import math
import sys
from contextlib import nullcontext
from pathlib import Path

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from ..errors import InputError
from ..files import atomic_write_text
from ..plots.sweep import strehl_vs_magnitude
from ..observation import BINNINGS, observation_for_magnitude
from ..sweep.derive import best_per_magnitude, derived_table, lut_csv
from ..sweep.grid import read_grid
from ..sweep.results import ResultsTable
from ..sweep.runner import run_sweep
from .common import CACHE_DIR, JSON_OUTPUT, NO_CACHE, default_cache_dir


def _json_row(row: dict) -> dict:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()}


def _render_derived(rows: list[dict], derived: list[dict], console: Console) -> None:
    t = Table(title="Best configuration per magnitude (highest Strehl) next to the paper's look-up table", title_justify="left")
    for col in ("R", "binning", "sub-ap.", "frame rate [Hz]", "Strehl", "paper: binning, frame rate [Hz]"):
        t.add_column(col, justify="right")
    for pick in best_per_magnitude(rows):
        paper = observation_for_magnitude(float(pick["magnitude"]))
        t.add_row(f"{pick['magnitude']:g}", str(pick["binning"]), str(BINNINGS[int(pick["binning"])]), f"{pick['frame_rate']:g}",
                  f"{pick['strehl']:.3f}", f"{paper.binning}, {paper.frame_rate_hz:g}")
    console.print(t)
    console.print("Derived look-up table (format of tables/magnitude_lut.csv):")
    print(lut_csv(derived), end="")


def sweep(
    grid: Path = typer.Argument(..., metavar="GRID.toml", help="The grid: loop run parameters (magnitude, seeing, wind, L0, duration, binning, frame_rate, tt_control, gain_method, band, seed, noise, vibrations, resonance, oversampling); a list is an axis."),
    scheduler: str | None = typer.Option(None, "--scheduler", metavar="ADDRESS", help="An existing Dask scheduler, e.g. tcp://host:8786 (default: a local cluster)."),
    workers: int | None = typer.Option(None, "--workers", help="Processes of the local cluster (default: one per core)."),
    out: Path = typer.Option(Path("sweep"), "--out", metavar="DIR", help="Folder of results.csv (and the figures, the derived table)."),
    resume: bool = typer.Option(False, "--resume", help="Complete an interrupted sweep: keep the finished rows of DIR/results.csv (checked line by line)."),
    plot: bool = typer.Option(False, "--plot", help="Write DIR/strehl_vs_magnitude.png."),
    derive_table: bool = typer.Option(False, "--derive-table", help="Print (and write DIR/derived_lut.csv) the best binning and rate per magnitude."),
    no_cache: bool = NO_CACHE,
    cache_dir: Path | None = CACHE_DIR,
    json_output: bool = JSON_OUTPUT,
) -> int:
    """Run a grid of simulated closed loops as Dask tasks and collect one row per case
    (parameters, Strehl, jitter, residual, run time, seed, version) in DIR/results.csv, appended
    case by case and put in the grid's order once every case has its row.  A failed or
    diverged case is a row with its reason; --resume completes an interrupted sweep without
    recomputing its finished rows (every row is checked).  Each distinct calibration is
    computed once and shared.  One sweep at a time per folder.  Exit status 0 once every case
    has a row, whatever its status.

    Example: soulctl sweep grid.toml --workers 2 --out sweep/ --plot --derive-table
    """
    cases = read_grid(grid)
    if workers is not None and not (1 <= workers <= 512):
        raise InputError(f"--workers must be in 1..512, got {workers}")
    if scheduler is not None and workers is not None:
        raise InputError("--workers sizes the local cluster; with --scheduler the scheduler's workers run the cases")
    if out.exists() and not out.is_dir():
        raise InputError(f"--out must be a folder, got the file {out}")
    if not out.parent.exists():
        raise InputError(f"--out: the folder {out.parent} does not exist")
    out.mkdir(exist_ok=True)
    cache = None if no_cache else str(cache_dir or default_cache_dir())
    show = not json_output and sys.stderr.isatty()
    progress = Progress(TextColumn("sweep"), BarColumn(), MofNCompleteColumn(), TextColumn("cases"), TextColumn("{task.fields[state]}"),
                        TimeElapsedColumn(), TimeRemainingColumn(), console=Console(stderr=True), transient=True)
    with progress if show else nullcontext():
        task = progress.add_task("sweep", total=None, state="") if show else None

        def started(n):
            if show:
                progress.update(task, total=n, state=f"running {min(n, workers or n)}")

        def finished(row, report):
            if show:
                left = progress.tasks[0].total - report.computed
                progress.update(task, completed=report.computed,
                                state=f"failed {report.failed}, diverged {report.diverged}, running {left}")

        report = run_sweep(cases, out, scheduler, workers, resume, cache, on_row=finished, on_start=started)
    rows = list(ResultsTable.read_rows(report.results).values())
    derived = derived_table(rows) if derive_table else None
    if derived is not None:
        atomic_write_text(out / "derived_lut.csv", lut_csv(derived))
    if plot:
        strehl_vs_magnitude(rows, out / "strehl_vs_magnitude.png")
    if json_output:
        print(json.dumps({"total": report.total, "skipped": report.skipped, "computed": report.computed, "failed": report.failed,
                          "diverged": report.diverged, "results": str(report.results), "notes": report.notes,
                          "rows": [_json_row(r) for r in report.rows], "derived_table": derived}))
        return 0
    console = Console()
    for note in report.notes:
        console.print(f"note: {note}")
    console.print(f"{report.total} cases: {report.computed} run now ({report.failed} failed, {report.diverged} diverged), "
                  f"{report.skipped} kept from an earlier run; results in {report.results}")
    for r in report.rows:
        if r["status"] != "ok":
            console.print(f"  case {r['case_id']} {r['status']}: {r['reason']}")
    if derived is not None:
        _render_derived(rows, derived, console)
    return 0
