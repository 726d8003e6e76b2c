"""Run a sweep's cases as Dask tasks: on a local cluster embedded in the command (processes,
one per core by default) or on an existing Dask scheduler (``tcp://host:8786``), the same
code either way.

In two steps, so that a sweep that cannot run creates nothing: ``plan_sweep`` checks the
output folder and the results file (with ``--resume``, its rows) and finds the cases to run;
``execute`` connects to the scheduler (or starts the local cluster), then creates the folder,
takes its lock (``results.results_lock``: one sweep per folder) and runs the cases.

Each distinct calibration (binning, modulation, modes, sampling, field of view) is one task, computed once
and handed by Dask to the cases that need it (no shared file system needed).  Rows are
appended by this process as the cases finish (``results.ResultsTable``): a worker that dies
loses no row (Dask runs its task again elsewhere) and duplicates none (one row per case id).
A case that fails or diverges is a row with its status and reason; the sweep goes on.  Once
every case has its row, the file is rewritten in the grid's order.  Beside the results,
``runs/<case_id>.toml`` holds each row's resolved run description: `soulctl loop run --config`
on it repeats the case's loop."""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError
from ..files import atomic_write_text, check_output_folder, check_output_path
from ..ranges import WAIT_WORKERS_S
from .case import DESCRIPTION_KEY, calibrate_case, calibration_setup, failed_row, run_case
from .results import ResultsTable, check_unlocked, results_lock
from .scheduler import CONNECT_TIMEOUT_S, probe

RESULTS = "results.csv"
RUNS_DIR = "runs"  # runs/<case_id>.toml: the resolved run description of each row


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


@dataclass
class SweepPlan:
    """What a sweep will do, found without creating or changing anything."""

    cases: list[dict]
    out_dir: Path
    resume: bool
    table: ResultsTable
    todo: list[tuple[str, dict]]  # (case id, case) to run, in the grid's order
    skipped: int  # this grid's finished rows found by --resume

    @property
    def total(self) -> int:
        return len(self.table.cases)


def plan_sweep(cases: list[dict], out_dir: str | Path, resume: bool = False, outputs: Iterable[str] = ()) -> SweepPlan:
    """Check, before anything is created, that the sweep can write ``out_dir``/results.csv
    (and the other ``outputs`` there) and, with ``resume``, read the rows already there;
    InputError otherwise.  A folder that does not exist yet must have a writable parent."""
    out = Path(out_dir)
    results = out / RESULTS
    if out.is_dir():
        check_output_folder(out, "--out", [RESULTS, *outputs])
        check_unlocked(out)
    elif os.path.lexists(out):
        raise InputError(f"--out must be a folder, got the file {out}" if out.is_file() else f"--out {out} is not a folder")
    else:
        check_output_path(out, "--out")  # the parent exists and can be written
    if os.path.lexists(results) and not resume:
        raise InputError(f"{results} exists: --resume to complete it, or choose another --out")
    table = ResultsTable(results, cases)
    done = table.resume() if resume else set()
    todo = [(cid, c) for cid, c in table.cases.items() if cid not in done]  # a case listed twice runs once
    return SweepPlan(cases, out, resume, table, todo, len(done))


def connect(stack: ExitStack, scheduler: str | None, workers: int | None, wait_workers_s: float = WAIT_WORKERS_S):
    """A Dask client: on ``scheduler`` (checked by ``scheduler.probe`` first; InputError naming
    it when unreachable, or when no worker joins it within ``wait_workers_s``), else on a local
    cluster of ``workers`` processes (default: one per core), one thread each."""
    from dask.distributed import Client, LocalCluster  # here: importing Dask costs every other command ~1 s

    if scheduler:
        address = probe(scheduler)
        try:
            client = stack.enter_context(Client(address, timeout=f"{CONNECT_TIMEOUT_S:g}s"))
        except Exception as e:  # noqa: BLE001 - what answers at the address is the user's: e.g. a worker (TypeError)
            raise InputError(
                f"cannot connect to the Dask scheduler at {scheduler} ({type(e).__name__}: {e}; is it the "
                f"scheduler's address?); nothing was run"
            ) from None
        try:
            client.wait_for_workers(1, timeout=wait_workers_s)
        except TimeoutError:
            raise InputError(
                f"the Dask scheduler at {scheduler} has no worker (none joined within {wait_workers_s:g} s): start "
                f"workers with 'dask worker {address}', or give --wait-workers; nothing was run"
            ) from None
        return client
    n = workers or local_workers()
    cluster = stack.enter_context(LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=40))
    return stack.enter_context(Client(cluster))


def local_workers() -> int:
    """The local cluster's default size: one worker per core this process may use."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def execute(
    plan: SweepPlan,
    scheduler: str | None = None,
    workers: int | None = None,
    cache_dir: str | None = None,
    on_row: Callable[[dict, SweepReport], None] | None = None,
    on_start: Callable[[int], None] | None = None,
    wait_workers_s: float = WAIT_WORKERS_S,
) -> SweepReport:
    """Run a plan (see the module): its folder is created only once the scheduler answered."""
    table = plan.table
    report = SweepReport(total=plan.total, skipped=plan.skipped, results=table.path)
    with ExitStack() as stack:
        client = connect(stack, scheduler, workers, wait_workers_s) if plan.todo else None
        done = _open_folder(stack, plan)
        todo = [(cid, c) for cid, c in table.cases.items() if cid not in done]
        report.skipped = len(done)
        report.notes = list(table.notes)
        table.open()
        stack.callback(table.close)
        if on_start:
            on_start(len(todo))

        record = _recorder(plan, report, on_row)
        if todo and client is None:  # rows removed since the plan (an edited file): start the cluster now
            client = connect(stack, scheduler, workers, wait_workers_s)
        if todo:
            assert client is not None  # connected above when there is work
            _submit_and_collect(client, todo, cache_dir, record)
        table.write_ordered()  # every case has its row: the grid's order
    return report


def _open_folder(stack: ExitStack, plan: SweepPlan) -> set:
    """Create the sweep's folder and take its lock; the case ids already done (--resume).  On
    an error a folder this call created is removed again."""
    table = plan.table
    created = not plan.out_dir.exists()
    try:
        plan.out_dir.mkdir(exist_ok=True)
    except OSError as e:
        raise InputError(f"--out: cannot create the folder {plan.out_dir}: {e.strerror or e}") from None
    try:
        stack.enter_context(results_lock(plan.out_dir))
        # under the lock, the file as it is now (another sweep may have written it since the plan)
        if os.path.lexists(table.path) and not plan.resume:
            raise InputError(f"{table.path} exists: --resume to complete it, or choose another --out")
        return table.resume() if plan.resume else set()
    except BaseException:
        if created:  # as it was: no folder (the lock released first)
            stack.close()
            _remove_empty(plan.out_dir)
        raise


def _recorder(plan: SweepPlan, report: SweepReport, on_row) -> Callable[[dict], None]:
    """What takes a finished row: its run description to runs/<case_id>.toml, the row to the
    results and the report."""

    def record(row: dict) -> None:
        description = row.pop(DESCRIPTION_KEY, None)
        if description is not None:  # the run the row measured: `loop run --config` repeats it
            (plan.out_dir / RUNS_DIR).mkdir(exist_ok=True)
            atomic_write_text(plan.out_dir / RUNS_DIR / f"{row['case_id']}.toml", description, immediate=True)
        plan.table.add(row)
        report.rows.append(row)
        report.computed += 1
        report.failed += row["status"] == "failed"
        report.diverged += row["status"] == "diverged"
        if on_row:
            on_row(row, report)

    return record


def _submit_and_collect(client, todo: list, cache_dir: str | None, record: Callable[[dict], None]) -> None:
    """One calibration task per distinct set-up, one task per case on it; rows recorded as the
    cases finish (an invalid case or a failed task is a failed row)."""
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


def _remove_empty(folder: Path) -> None:
    try:
        folder.rmdir()
    except OSError:
        pass


def run_sweep(
    cases: list[dict],
    out_dir: str | Path,
    scheduler: str | None = None,
    workers: int | None = None,
    resume: bool = False,
    cache_dir: str | None = None,
    on_row: Callable[[dict, SweepReport], None] | None = None,
    on_start: Callable[[int], None] | None = None,
) -> SweepReport:
    """Run ``cases`` (from ``grid.parse_grid``), writing ``out_dir/results.csv``."""
    return execute(plan_sweep(cases, out_dir, resume), scheduler, workers, cache_dir, on_row, on_start)
