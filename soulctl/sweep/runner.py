"""Run a sweep's cases as Dask tasks: on a local cluster embedded in the command (processes,
one per core by default) or on an existing Dask scheduler (``tcp://host:8786``), the same
code either way.

Each distinct calibration (binning, modulation, modes, sampling) is one task, computed once
and handed by Dask to the cases that need it (no shared file system needed).  Rows are
appended by this process as the cases finish (``results.ResultsTable``), under the folder's
lock (``results.results_lock``: one sweep per folder): a worker that dies loses no row (Dask
runs its task again elsewhere) and duplicates none (one row per case id).  A case that fails
or diverges is a row with its status and reason; the sweep goes on.  Once every case has its
row, the file is rewritten in the grid's order."""

from __future__ import annotations

import os
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError
from .case import calibrate_case, calibration_setup, failed_row, run_case
from .results import ResultsTable, results_lock

CONNECT_TIMEOUT_S = 5


@dataclass
class SweepReport:
    total: int
    skipped: int  # finished rows found by --resume
    computed: int = 0
    failed: int = 0
    diverged: int = 0
    rows: list[dict] = field(default_factory=list)  # this run's rows, in finishing order
    results: Path | None = None
    notes: list[str] = field(default_factory=list)  # what --resume found (an incomplete last line, other columns)


def connect(stack: ExitStack, scheduler: str | None, workers: int | None):
    """A Dask client: on ``scheduler`` (InputError naming it when unreachable), else on a
    local cluster of ``workers`` processes (default: one per core), one thread each."""
    from dask.distributed import Client, LocalCluster  # here: importing Dask costs every other command ~1 s

    if scheduler:
        try:
            return stack.enter_context(Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s"))
        except (OSError, TimeoutError, ValueError) as e:  # ValueError: not an address
            raise InputError(f"cannot reach the Dask scheduler at {scheduler} ({type(e).__name__}); nothing was run") from None
    n = workers or (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)
    cluster = stack.enter_context(LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                                               silence_logs=40))
    return stack.enter_context(Client(cluster))


def run_sweep(cases: list[dict], out_dir: Path, scheduler: str | None = None, workers: int | None = None,
              resume: bool = False, cache_dir: str | None = None, on_row: Callable[[dict, "SweepReport"], None] | None = None,
              on_start: Callable[[int], None] | None = None) -> SweepReport:
    """Run ``cases`` (from ``grid.parse_grid``), writing ``out_dir/results.csv``."""
    table = ResultsTable(Path(out_dir) / "results.csv", cases)
    if table.path.exists() and not resume:
        raise InputError(f"{table.path} exists: --resume to complete it, or choose another --out")
    with ExitStack() as stack:
        stack.enter_context(results_lock(out_dir))
        done = table.resume() if resume else set()
        todo = [(cid, c) for cid, c in table.cases.items() if cid not in done]  # a case listed twice runs once
        report = SweepReport(total=len(table.cases), skipped=len(done), results=table.path, notes=list(table.notes))
        client = connect(stack, scheduler, workers) if todo else None  # before the file is created
        table.open()
        stack.callback(table.close)
        if on_start:
            on_start(len(todo))

        def record(row: dict) -> None:
            table.add(row)
            report.rows.append(row)
            report.computed += 1
            report.failed += row["status"] == "failed"
            report.diverged += row["status"] == "diverged"
            if on_row:
                on_row(row, report)

        calibrations, futures = {}, {}
        for cid, case in todo:
            try:
                setup = calibration_setup(case)
            except InputError as e:  # the case itself is invalid: a failed row, no task
                record(failed_row(case, str(e)))
                continue
            key = setup.key()
            if key not in calibrations:
                calibrations[key] = client.submit(calibrate_case, setup, cache_dir, key=f"calibration-{key}", pure=False)
            futures[client.submit(run_case, case, calibrations[key], cache_dir, key=f"case-{cid}", pure=False)] = case
        if futures:
            from dask.distributed import as_completed

            for future in as_completed(futures):
                case = futures[future]
                try:
                    row = future.result()
                except Exception as e:  # e.g. the calibration failed, or the task's workers kept dying
                    row = failed_row(case, f"{type(e).__name__}: {e}")
                record(row)
        table.write_ordered()  # every case has its row: the grid's order
    return report
