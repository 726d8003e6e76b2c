"""Run a sweep's cases as Dask tasks: on a local cluster embedded in the command (processes,
one per core by default) or on an existing Dask scheduler (``tcp://host:8786``), the same
code either way.

Each distinct calibration (binning, modulation, modes, sampling) is one task, computed once
and handed by Dask to the cases that need it (no shared file system needed).  Rows are
written by this process as the cases finish (``results.ResultsTable``): a worker that dies
loses no row (Dask runs its task again elsewhere) and duplicates none (one row per case id).
A case that fails or diverges is a row with its status and reason; the sweep goes on."""

from __future__ import annotations

import os
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError
from .case import calibrate_case, calibration_setup, failed_row, run_case
from .grid import case_id
from .results import ResultsTable

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
    from dask.distributed import as_completed

    ids = [case_id(c) for c in cases]
    table = ResultsTable(Path(out_dir) / "results.csv", ids)
    if table.path.exists() and not resume:
        raise InputError(f"{table.path} exists: --resume to complete it, or choose another --out")
    done = table.resume() if resume else set()
    todo = list({cid: c for cid, c in zip(ids, cases) if cid not in done}.items())  # a case listed twice runs once
    report = SweepReport(total=len(set(ids)), skipped=len(done), results=table.path)
    if on_start:
        on_start(len(todo))
    if not todo:
        table.write()
        return report

    def record(row: dict) -> None:
        table.add(row)
        report.rows.append(row)
        report.computed += 1
        report.failed += row["status"] == "failed"
        report.diverged += row["status"] == "diverged"
        if on_row:
            on_row(row, report)

    with ExitStack() as stack:
        client = connect(stack, scheduler, workers)
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
        for future in as_completed(futures):
            case = futures[future]
            try:
                row = future.result()
            except Exception as e:  # e.g. the calibration failed, or the task's workers kept dying
                row = failed_row(case, f"{type(e).__name__}: {e}")
            record(row)
    return report
