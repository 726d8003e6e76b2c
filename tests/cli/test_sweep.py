"""`soulctl sweep` on Dask: a small grid on a local 2-worker cluster equals the same cases run one
by one with `loop run`; --resume completes a sweep without recomputing its rows; a worker
killed mid-sweep loses and duplicates no row; an external scheduler; one-line errors."""

import json
import signal
import socket
import subprocess
import sys
import time

import psutil
import pytest

from soulctl.cli.app import main
from soulctl.sweep.grid import case_id, parse_grid
from soulctl.sweep.results import ResultsTable
from soulctl.sweep.runner import run_sweep

# 2 magnitudes x 2 seeings at 10x10 and 13x13 sub-apertures, 40-px pupil, 0.3 s each.
GRID = "magnitude = [16.0, 17.0]\nseeing = [0.8, 1.2]\noversampling = 1\nduration = 0.3\nseed = 2\n"


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("sweep-cache")


@pytest.fixture
def grid(tmp_path):
    path = tmp_path / "grid.toml"
    path.write_text(GRID)
    return path


def cli(args, capsys, cache_dir):
    status = main([*args, "--cache-dir", str(cache_dir)])
    out, err = capsys.readouterr()
    return status, out, err


def test_local_cluster_equals_loop_run_case_by_case_and_resume(grid, tmp_path, capsys, cache_dir):
    out_dir = tmp_path / "out"
    status, out, err = cli(["sweep", str(grid), "--workers", "2", "--out", str(out_dir), "--json", "--plot", "--derive-table"],
                           capsys, cache_dir)
    assert status == 0, err
    report = json.loads(out)
    assert (report["total"], report["computed"], report["failed"], report["skipped"]) == (4, 4, 0, 0)
    rows = ResultsTable.read_rows(out_dir / "results.csv")
    assert len(rows) == 4
    for row in rows.values():
        args = ["loop", "run", "--mag", f"{row['magnitude']:g}", "--seeing", f"{row['seeing']:g}", "--oversampling", "1",
                "--duration", "0.3", "--seed", "2", "--json"]
        status, out, _ = cli(args, capsys, cache_dir)
        m = json.loads(out)["metrics"]
        assert (row["strehl"], row["tt_jitter_mas"], row["residual_nm"]) == (m["strehl"], m["tt_jitter_mas"], m["residual_nm"])
        assert row["status"] == "ok" and row["seed"] == 2 and row["run_seconds"] > 0 and row["soulctl_version"]
    assert (out_dir / "strehl_vs_magnitude.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out_dir / "derived_lut.csv").read_text().count("\n") >= 3
    assert [p["binning"] for p in report["derived_table"]] == [3, 4]  # the table's binnings for R16 and R17

    # without --resume an existing results file is refused; with it, only the missing row runs
    status, _, err = cli(["sweep", str(grid), "--out", str(out_dir)], capsys, cache_dir)
    assert status == 2 and "--resume" in err
    before = (out_dir / "results.csv").read_text().splitlines()
    (out_dir / "results.csv").write_text("\n".join(before[:2] + before[3:]) + "\n")  # an interrupted sweep
    status, out, err = cli(["sweep", str(grid), "--workers", "1", "--out", str(out_dir), "--resume", "--json"], capsys, cache_dir)
    assert status == 0, err
    report = json.loads(out)
    assert (report["computed"], report["skipped"]) == (1, 3)
    after = (out_dir / "results.csv").read_text().splitlines()
    assert [ln.split(",")[:20] for ln in after] == [ln.split(",")[:20] for ln in before]  # same rows, same numbers


def _worker_processes():
    """The local cluster's worker processes (spawned by multiprocessing; not its resource tracker)."""
    return [p for p in psutil.Process().children(recursive=True) if "spawn_main" in " ".join(p.cmdline())]


def test_a_killed_worker_loses_and_duplicates_no_row(tmp_path, cache_dir):
    cases = parse_grid({"magnitude": [16.0, 17.0, 17.5], "seeing": [0.8, 1.0], "oversampling": 1, "duration": 0.5})
    killed = []

    def kill_one(row, report):
        if not killed:
            victims = _worker_processes()
            if victims:
                victims[-1].send_signal(signal.SIGKILL)
                killed.append(victims[-1].pid)

    report = run_sweep(cases, tmp_path, workers=2, cache_dir=str(cache_dir), on_row=kill_one)
    assert killed, "no worker process was found to kill"
    rows = ResultsTable.read_rows(tmp_path / "results.csv")
    assert sorted(rows) == sorted(case_id(c) for c in cases)
    assert len((tmp_path / "results.csv").read_text().splitlines()) == 1 + len(cases)
    assert report.computed == len(cases) and all(r["status"] == "ok" for r in rows.values()), [r["reason"] for r in rows.values()]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_an_external_scheduler_and_worker(grid, tmp_path, capsys, cache_dir):
    """`dask scheduler` and `dask worker` started by hand (as the README shows), then the sweep
    sent to them with --scheduler."""
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--dashboard-address", ":0"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        time.sleep(2)
        procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", address, "--nworkers", "1",
                                       "--nthreads", "1", "--no-dashboard"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        status, out, err = cli(["sweep", str(grid), "--scheduler", address, "--out", str(tmp_path / "ext"), "--json"], capsys, cache_dir)
        assert status == 0, err
        assert json.loads(out)["computed"] == 4
    finally:
        for p in procs[::-1]:
            p.send_signal(signal.SIGINT)
        for p in procs[::-1]:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()


@pytest.mark.parametrize("text, args, message", [
    ("magnitude = [", [], "is not valid TOML"),
    ("magnitude = 12\ncolour = 1\n", [], "unknown parameter colour"),
    ("", [], "is empty"),
    ("magnitude = 12\n", ["--scheduler", "tcp://127.0.0.1:9"], "cannot reach the Dask scheduler at tcp://127.0.0.1:9"),
    ("magnitude = 12\n", ["--workers", "0"], "--workers must be in 1..512"),
    # the ranges are soulctl.ranges' (wind 0 crashed inside the loop; L0 below 0.5 m is not accepted by loop run)
    ("magnitude = 12\nwind = [5, 0]\n", [], "wind must be a number in 0..100 m/s (> 0), got 0"),
    ("magnitude = 12\nL0 = 0.1\n", [], "L0 must be a number in 0.5..10000 m, got 0.1"),
    ("magnitude = 18.6\n", [], "magnitude must be a number in 0..18.5, got 18.6"),
    ("magnitude = 12\n", ["--scheduler", "http://127.0.0.1:notaport"], "cannot reach the Dask scheduler"),
])
def test_bad_input_exits_2_and_runs_nothing(text, args, message, tmp_path, capsys, cache_dir):
    path = tmp_path / "grid.toml"
    path.write_text(text)
    out_dir = tmp_path / "out"
    status, _, err = cli(["sweep", str(path), "--out", str(out_dir), *args], capsys, cache_dir)
    assert status == 2 and message in err and err.count("\n") == 1
    assert not (out_dir / "results.csv").exists()


def test_missing_grid_file(tmp_path, capsys, cache_dir):
    status, _, err = cli(["sweep", str(tmp_path / "none.toml")], capsys, cache_dir)
    assert status == 2 and "grid file not found" in err
