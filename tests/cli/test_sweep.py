"""`soulctl sweep` on Dask: a small grid on a local 2-worker cluster equals the same cases run one
by one with `loop run`; --resume completes a sweep without recomputing its rows; a worker
killed mid-sweep loses and duplicates no row; an external scheduler; one-line errors, nothing
created, for a bad grid, a bad or silent scheduler, a results file that cannot be resumed or a
folder another sweep is writing; rows appended one line at a time; the estimate and the
question before a long sweep."""

import http.server
import json
import os
import random
import signal
import socket
import socketserver
import subprocess
import sys
import threading
import time
import tomllib

import psutil
import pytest
from cheap import CHEAP_PYRAMID

from soulctl.cli.app import main
from soulctl.sweep import scheduler as dask_scheduler
from soulctl.sweep.case import failed_row
from soulctl.sweep.grid import case_id, parse_grid
from soulctl.sweep.results import COLUMNS, ResultsTable, csv_line
from soulctl.sweep.runner import run_sweep

# 2 magnitudes x 2 seeings at 10x10 and 13x13 sub-apertures, 40-px pupil, 0.3 s each.
GRID = "magnitude = [16.0, 17.0]\nseeing = [0.8, 1.2]\noversampling = 1\nwfs_field = 0\nduration = 0.3\nseed = 2\n"
# The smallest cases: 10x10 sub-apertures, 40-px pupil, 0.05 s.
TINY = "magnitude = [16.6, 17.0, 17.5]\nbinning = 4\noversampling = 1\nwfs_field = 0\nduration = 0.05\n"


@pytest.fixture
def grid(tmp_path):
    path = tmp_path / "grid.toml"
    path.write_text(GRID)
    return path


def cli(args, capsys, cache_dir):
    status = main([*args, "--cache-dir", str(cache_dir)])
    out, err = capsys.readouterr()
    return status, out, err


@pytest.mark.slow
def test_local_cluster_equals_loop_run_case_by_case_and_resume(grid, tmp_path, capsys, cache_dir):
    out_dir = tmp_path / "out"
    status, out, err = cli(
        ["sweep", str(grid), "--workers", "2", "--out", str(out_dir), "--json", "--plot", "--derive-table"], capsys, cache_dir
    )
    assert status == 0, err
    report = json.loads(out)
    assert (report["total"], report["computed"], report["failed"], report["skipped"]) == (4, 4, 0, 0)
    rows = ResultsTable.read_rows(out_dir / "results.csv")
    assert len(rows) == 4
    for row in rows.values():
        args = [
            "loop",
            "run",
            "--mag",
            f"{row['magnitude']:g}",
            "--seeing",
            f"{row['seeing']:g}",
            *CHEAP_PYRAMID,
            "--duration",
            "0.3",
            "--seed",
            "2",
            "--json",
        ]
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
    out = []
    for p in psutil.Process().children(recursive=True):
        try:
            if "spawn_main" in " ".join(p.cmdline()):
                out.append(p)
        except psutil.Error:  # a child that ended (a zombie of an earlier cluster) is not a worker
            pass
    return out


@pytest.mark.slow
def test_a_killed_worker_loses_and_duplicates_no_row(tmp_path, cache_dir):
    cases = parse_grid({"magnitude": [16.0, 17.0, 17.5], "seeing": [0.8, 1.0], "oversampling": 1, "wfs_field": 0, "duration": 0.5})
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


def _start_scheduler(port: int, cwd) -> subprocess.Popen:
    """`dask scheduler` on 127.0.0.1:port, returned once it accepts connections (a fixed
    2 s sleep was not enough on a loaded machine: the sweep then found nobody listening)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1", "--port", str(port), "--dashboard-address", ":0"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        cwd=cwd,
    )
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"the Dask scheduler exited with status {proc.returncode}"
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            return proc
        except OSError:
            time.sleep(0.2)
    proc.kill()
    raise AssertionError(f"the Dask scheduler did not listen on 127.0.0.1:{port} within 60 s")


@pytest.mark.slow
def test_an_external_scheduler_and_worker(grid, tmp_path, capsys, cache_dir):
    """`dask scheduler` and `dask worker` started by hand (as the README shows), then the sweep
    sent to them with --scheduler."""
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    procs = [_start_scheduler(port, tmp_path)]
    try:
        procs.append(
            subprocess.Popen(
                [sys.executable, "-m", "distributed.cli.dask_worker", address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard"],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                cwd=tmp_path,
            )
        )
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


# ------------------------------------------------------------------- bad input: exit 2, nothing created


@pytest.mark.parametrize(
    "text, args, message",
    [
        ("magnitude = [", [], "is not valid TOML"),
        ("magnitude = 12\ncolour = 1\n", [], "unknown parameter colour"),
        ("", [], "is empty"),
        (
            "magnitude = 12\n",
            ["--scheduler", "tcp://127.0.0.1:9"],
            "cannot reach the Dask scheduler at tcp://127.0.0.1:9: connection refused",
        ),
        ("magnitude = 12\n", ["--workers", "0"], "--workers (2 per core at most) must be in 1.."),
        ("magnitude = 12\n", ["--workers", "512"], "--workers (2 per core at most) must be in 1.."),
        # the ranges are soulctl.ranges' (wind 0 crashed inside the loop; L0 below 0.5 m is not accepted by loop run)
        ("magnitude = 12\nwind = [5, 0]\n", [], "wind must be in 0..100 m/s (> 0), got 0"),
        ("magnitude = 12\nL0 = 0.1\n", [], "L0 must be in 0.5..10000 m, got 0.1"),
        ("magnitude = 18.6\n", [], "magnitude must be in 0..18.5, got 18.6"),
        # schemes other than tcp:// are refused (they gave TypeError tracebacks), and malformed addresses
        (
            "magnitude = 12\n",
            ["--scheduler", "ucx://127.0.0.1:8786"],
            "--scheduler must be tcp://HOST:PORT, got 'ucx://127.0.0.1:8786' (ucx://",
        ),
        (
            "magnitude = 12\n",
            ["--scheduler", "tls://127.0.0.1:8786"],
            "--scheduler must be tcp://HOST:PORT, got 'tls://127.0.0.1:8786' (tls://: TLS",
        ),
        ("magnitude = 12\n", ["--scheduler", "inproc://127.0.0.1/1/2"], "(inproc://: inproc:// only exists inside one Python process)"),
        ("magnitude = 12\n", ["--scheduler", "http://127.0.0.1:notaport"], "--scheduler must be tcp://HOST:PORT"),
        ("magnitude = 12\n", ["--scheduler", "tcp://127.0.0.1"], "--scheduler must be tcp://HOST:PORT (PORT 1..65535"),
        ("magnitude = 12\n", ["--scheduler", "tcp://127.0.0.1:99999"], "--scheduler must be tcp://HOST:PORT (PORT 1..65535"),
        ("magnitude = 12\n", ["--scheduler", "tcp://[::1:8786"], "--scheduler must be tcp://HOST:PORT"),
        ("magnitude = 12\n", ["--scheduler", "tcp:// 127.0.0.1:8786"], "--scheduler must be tcp://HOST:PORT"),
    ],
)
def test_bad_input_exits_2_runs_nothing_and_creates_no_folder(text, args, message, tmp_path, capsys, cache_dir):
    path = tmp_path / "grid.toml"
    path.write_text(text)
    out_dir = tmp_path / "out"
    status, out, err = cli(["sweep", str(path), "--out", str(out_dir), *args], capsys, cache_dir)
    assert status == 2 and message in err and err.count("\n") == 1, err
    assert not out_dir.exists()


def test_missing_grid_file(tmp_path, capsys, cache_dir):
    status, _, err = cli(["sweep", str(tmp_path / "none.toml")], capsys, cache_dir)
    assert status == 2 and "grid file not found" in err


def test_an_out_folder_that_cannot_be_made_is_refused_first(tmp_path, capsys, cache_dir):
    grid = tmp_path / "grid.toml"
    grid.write_text("magnitude = 12\n")
    (tmp_path / "file").write_text("x")
    status, _, err = cli(["sweep", str(grid), "--out", str(tmp_path / "file" / "out")], capsys, cache_dir)
    assert status == 2 and "--out" in err and err.count("\n") == 1
    status, _, err = cli(["sweep", str(grid), "--out", str(tmp_path / "none" / "out")], capsys, cache_dir)
    assert status == 2 and "does not exist" in err and not (tmp_path / "none").exists()
    out = tmp_path / "out"
    (out / "strehl_vs_magnitude.png").mkdir(parents=True)
    status, _, err = cli(["sweep", str(grid), "--out", str(out), "--plot"], capsys, cache_dir)
    assert status == 2 and "strehl_vs_magnitude.png is a directory" in err
    assert sorted(p.name for p in out.iterdir()) == ["strehl_vs_magnitude.png"]


# ------------------------------------------------------------------- schedulers that do not answer


class _Listener:
    """A TCP listener on 127.0.0.1 that accepts connections and then stays silent, or sends
    ``answer`` (bytes) to each."""

    def __init__(self, answer: bytes | None = None):
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(16)
        self.port = self.sock.getsockname()[1]
        self.answer, self.conns, self.accepted = answer, [], []
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self):
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            self.conns.append(conn)
            self.accepted.append(time.monotonic())
            if self.answer:
                conn.sendall(self.answer)

    def close(self):
        for c in self.conns:
            c.close()
        self.sock.close()


@pytest.mark.slow
def test_a_silent_listener_is_refused_within_the_bound_and_the_process_exits(tmp_path):
    """The connect bound (10 s) holds for a listener that never speaks, and nothing lingers:
    the command line, in its own process, ends within the bound of the connection (and within
    ~15 s of its start, Python's start-up and imports included: 20 s allowed on a busy machine)."""
    listener = _Listener()
    grid = tmp_path / "grid.toml"
    grid.write_text("magnitude = 12\n")
    address = f"tcp://127.0.0.1:{listener.port}"
    try:
        t0 = time.monotonic()
        proc = subprocess.run(
            [sys.executable, "-m", "soulctl.cli.app", "sweep", str(grid), "--scheduler", address, "--out", str(tmp_path / "out")],
            capture_output=True,
            text=True,
            timeout=60,
            cwd=tmp_path,
        )  # the installed package, not the source folder
        t1 = time.monotonic()
    finally:
        listener.close()
    assert proc.returncode == 2, proc.stderr
    assert len(listener.accepted) == 1 and t1 - listener.accepted[0] < dask_scheduler.CONNECT_TIMEOUT_S + 1.5
    assert proc.stderr == (
        f"soulctl: error: cannot reach the Dask scheduler at {address}: no answer from a Dask scheduler "
        f"within {dask_scheduler.CONNECT_TIMEOUT_S:g} s; nothing was run\n"
    )
    assert dask_scheduler.CONNECT_TIMEOUT_S <= 10 and t1 - t0 < 20
    assert not (tmp_path / "out").exists()


class _Http(http.server.BaseHTTPRequestHandler):
    def do_GET(self):
        self.send_response(200)
        self.end_headers()
        self.wfile.write(b"<html>dashboard</html>")

    def log_message(self, *args):
        pass


@pytest.mark.parametrize(
    "server, message",
    [
        ("http", "no answer from a Dask scheduler within 2 s"),  # e.g. the dashboard's port: waits for a request
        ("random", "the listener there is not a Dask scheduler (it announced a first message of"),  # once: exabytes
        ("http-greeting", "the listener there is not a Dask scheduler (it announced a first message of"),
        ("closes", "the listener there is not a Dask scheduler (it closed the connection without a handshake)"),
    ],
)
def test_a_listener_that_is_not_a_scheduler_is_refused(server, message, tmp_path, capsys, cache_dir, monkeypatch):
    monkeypatch.setattr(dask_scheduler, "CONNECT_TIMEOUT_S", 2.0)
    if server == "http":
        httpd = socketserver.ThreadingTCPServer(("127.0.0.1", 0), _Http)
        threading.Thread(target=httpd.serve_forever, daemon=True).start()
        port, close = httpd.server_address[1], lambda: (httpd.shutdown(), httpd.server_close())
    elif server == "closes":
        sock = socket.socket()
        sock.bind(("127.0.0.1", 0))
        sock.listen(4)

        def serve():
            try:
                while True:
                    sock.accept()[0].close()
            except OSError:
                pass

        threading.Thread(target=serve, daemon=True).start()
        port, close = sock.getsockname()[1], sock.close
    else:
        answer = random.Random(1).randbytes(4096) if server == "random" else b"HTTP/1.1 400 Bad Request\r\n\r\n"
        listener = _Listener(answer)
        port, close = listener.port, listener.close
    grid = tmp_path / "grid.toml"
    grid.write_text("magnitude = 12\n")
    try:
        t0 = time.monotonic()
        status, _, err = cli(
            ["sweep", str(grid), "--scheduler", f"tcp://127.0.0.1:{port}", "--out", str(tmp_path / "out")], capsys, cache_dir
        )
        elapsed = time.monotonic() - t0
    finally:
        close()
    assert status == 2 and f"cannot reach the Dask scheduler at tcp://127.0.0.1:{port}: {message}" in err, err
    assert err.count("\n") == 1 and elapsed < 5
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------- --resume checks the rows


def _finished_results(path, text, edit=lambda lines: lines, bom=False, newline="\n"):
    """A results file in which every case of the grid ``text`` is finished (no case to run)."""
    cases = parse_grid(tomllib.loads(text))
    lines = [",".join(COLUMNS)]
    for c in cases:
        row = {**failed_row(c, ""), "status": "ok", "strehl": 0.25, "tt_jitter_mas": 4.0, "residual_nm": 150.0, "run_seconds": 1.0}
        lines.append(csv_line(row, COLUMNS).rstrip("\n"))
    lines = edit(lines)
    path.parent.mkdir(exist_ok=True)
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + (newline.join(lines) + newline).encode())
    return cases


def test_resume_refuses_an_ok_row_without_metrics_naming_its_line(tmp_path, capsys, cache_dir):
    grid = tmp_path / "grid.toml"
    grid.write_text(TINY)
    results = tmp_path / "out" / "results.csv"

    def empty_strehl(lines):
        lines[2] = lines[2].replace("0.25,4.0,150.0,ok", ",4.0,150.0,ok")
        return lines

    _finished_results(results, TINY, empty_strehl)
    before = results.read_bytes()
    status, _, err = cli(["sweep", str(grid), "--out", str(tmp_path / "out"), "--resume"], capsys, cache_dir)
    assert status == 2 and err.count("\n") == 1
    assert f"results file {results}, line 3: status ok with an empty strehl" in err and "set its status to failed" in err
    assert results.read_bytes() == before and sorted(p.name for p in results.parent.iterdir()) == ["results.csv"]


def test_resume_refuses_a_parameter_out_of_range_naming_its_line(tmp_path, capsys, cache_dir):
    grid = tmp_path / "grid.toml"
    grid.write_text(TINY)
    results = tmp_path / "out" / "results.csv"
    _finished_results(
        results, TINY, lambda lines: [*lines, lines[1].replace(",1.0,8.0,", ",11.0,8.0,").replace(lines[1][:16], "0123456789abcdef")]
    )
    status, _, err = cli(["sweep", str(grid), "--out", str(tmp_path / "out"), "--resume"], capsys, cache_dir)
    assert status == 2 and "line 5: seeing must be in 0.05..10 arcsec, got 11" in err


def test_resume_accepts_a_spreadsheets_file_and_keeps_its_columns(tmp_path, capsys, cache_dir):
    """A byte-order mark, CRLF line ends and a column of the user's own: resumed, the column kept."""
    grid = tmp_path / "grid.toml"
    grid.write_text(TINY)
    results = tmp_path / "out" / "results.csv"
    cases = _finished_results(
        results, TINY, lambda lines: [lines[0] + ",notes"] + [ln + f",note {i}" for i, ln in enumerate(lines[1:])], bom=True, newline="\r\n"
    )
    status, out, err = cli(["sweep", str(grid), "--out", str(tmp_path / "out"), "--resume", "--json"], capsys, cache_dir)
    assert status == 0, err
    report = json.loads(out)
    assert (report["skipped"], report["computed"]) == (3, 0) and any("notes" in n for n in report["notes"])
    lines = results.read_text().splitlines()
    assert lines[0].endswith(",notes") and [ln.rsplit(",", 1)[1] for ln in lines[1:]] == ["note 0", "note 1", "note 2"]
    assert [ln.split(",")[0] for ln in lines[1:]] == [case_id(c) for c in cases]


# ------------------------------------------------------------------- rows appended, one line each


@pytest.mark.slow
def test_rows_are_appended_a_line_at_a_time_and_a_torn_line_is_resumed(tmp_path, capsys, cache_dir, monkeypatch):
    """Each finished case appends one complete line to the same file (no rewrite per case); the
    file is put in the grid's order at the end; an incomplete last line (a crash during a
    write) is ignored by --resume, removed, and its case run again."""
    grid = tmp_path / "grid.toml"
    grid.write_text(TINY)
    out = tmp_path / "out"
    results = out / "results.csv"
    seen = []
    add = ResultsTable.add

    def spy(self, row):
        add(self, row)
        st = os.stat(results)
        seen.append((st.st_ino, results.read_bytes()))

    monkeypatch.setattr(ResultsTable, "add", spy)
    status, _, err = cli(["sweep", str(grid), "--workers", "1", "--out", str(out), "--json"], capsys, cache_dir)
    assert status == 0, err
    assert len(seen) == 3 and len({ino for ino, _ in seen}) == 1  # one file, appended to
    for (_, a), (_, b) in zip(seen, seen[1:]):
        assert b.startswith(a) and b[len(a) :].count(b"\n") == 1 and b.endswith(b"\n")
    final = results.read_text().splitlines()
    assert [ln.split(",")[0] for ln in final[1:]] == [
        case_id(c) for c in parse_grid({"magnitude": [16.6, 17.0, 17.5], "binning": 4, "oversampling": 1, "wfs_field": 0, "duration": 0.05})
    ]
    # a crash in the middle of the last write: the file ends with part of a line
    results.write_text("\n".join(final[:-1]) + "\n" + final[-1][:50])
    status, out_text, err = cli(["sweep", str(grid), "--workers", "1", "--out", str(out), "--resume", "--json"], capsys, cache_dir)
    assert status == 0, err
    report = json.loads(out_text)
    assert (report["skipped"], report["computed"]) == (2, 1)
    assert any("line 4: an incomplete last row (an interrupted write) is ignored" in n for n in report["notes"])
    again = results.read_text().splitlines()
    assert [ln.split(",")[:20] for ln in again] == [ln.split(",")[:20] for ln in final]


# ------------------------------------------------------------------- one sweep per folder


def test_a_second_sweep_into_the_same_folder_is_refused(tmp_path, capsys, cache_dir):
    grid = tmp_path / "grid.toml"
    grid.write_text(TINY)
    out = tmp_path / "out"
    out.mkdir()
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time\nfrom soulctl.sweep.results import results_lock\n"
            "with results_lock(sys.argv[1]):\n    print('locked', flush=True)\n    time.sleep(60)\n",
            str(out),
        ],
        stdout=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        for extra in ([], ["--resume"]):
            status, _, err = cli(["sweep", str(grid), "--workers", "1", "--out", str(out), *extra], capsys, cache_dir)
            assert status == 2 and err.count("\n") == 1
            assert f"another soulctl sweep (process {holder.pid}) is writing {out / 'results.csv'}" in err
        assert sorted(p.name for p in out.iterdir()) == [".results.csv.lock"]
    finally:
        holder.kill()
        holder.wait()


# ------------------------------------------------------------------- the estimate, and the question

BIG = "magnitude = [16.6, 17.0, 17.5]\nseeing = [0.6, 0.8, 1.0, 1.2, 1.4]\nseed = {seeds}\nduration = 0.5\n"


@pytest.mark.slow
def test_the_estimate_is_printed_and_in_the_json(tmp_path, capsys, cache_dir):
    grid = tmp_path / "grid.toml"
    grid.write_text(TINY)
    status, out, err = cli(["sweep", str(grid), "--workers", "1", "--out", str(tmp_path / "a")], capsys, cache_dir)
    assert status == 0, err
    first = err.splitlines()[0]  # on stderr, when the run starts
    assert first.startswith("estimate: 3 cases, ") and " frames, 1 calibration: " in first and "on 1 worker" in first
    status, out, err = cli(["sweep", str(grid), "--workers", "1", "--out", str(tmp_path / "b"), "--json"], capsys, cache_dir)
    est = json.loads(out)["estimate"]
    assert est["cases"] == 3 and est["calibrations"] == 1 and est["workers"] == 1 and est["cpu_seconds"] > 0
    assert est["frames"] > 0 and est["source"].startswith("bench/results/frame_cost.json")


class _Terminal:
    def __init__(self, answer):
        self.answer, self.asked = answer, 0

    def isatty(self):
        return True

    def readline(self):
        self.asked += 1
        return self.answer


@pytest.mark.parametrize(
    "answer, args, terminal, asked, status, message",
    [
        ("n\n", [], True, 1, 2, "sweep not started (not confirmed; --yes starts a long sweep without asking)"),
        ("", [], True, 1, 2, "sweep not started"),  # end of input
        ("y\n", [], True, 1, 2, "reached the run"),
        ("n\n", ["--yes"], True, 0, 2, "reached the run"),
        ("n\n", [], False, 0, 2, "reached the run"),  # not a terminal: no question
        ("n\n", ["--json"], True, 1, 2, "sweep not started"),  # the estimate in the question
    ],
)
def test_a_long_sweep_asks_on_a_terminal(answer, args, terminal, asked, status, message, tmp_path, capsys, cache_dir, monkeypatch):
    import soulctl.cli.sweep as sweep_cli
    from soulctl.errors import InputError

    def stub(*a, **k):
        raise InputError("reached the run")

    monkeypatch.setattr(sweep_cli, "execute", stub)
    stdin = _Terminal(answer)
    if not terminal:
        stdin.isatty = lambda: False
    monkeypatch.setattr(sys, "stdin", stdin)
    grid = tmp_path / "grid.toml"
    grid.write_text(BIG.format(seeds=list(range(1, 2001))))  # 30 000 cases of 0.5 s
    t0 = time.monotonic()
    code, out, err = cli(["sweep", str(grid), "--out", str(tmp_path / "out"), "--workers", "2", *args], capsys, cache_dir)
    assert time.monotonic() - t0 < 20
    assert code == status and message in err and stdin.asked == asked
    # the estimate goes to stderr, with the question when there is one, else when the run starts
    assert out == "" and ("estimate: 30000 cases, " in err) == bool(asked)
    assert ("This sweep takes more than 1 h of CPU. Start it? [y/N]" in err) == bool(asked)
    assert not (tmp_path / "out").exists()


def test_a_scheduler_without_workers_is_refused_within_the_wait(grid, tmp_path, capsys, cache_dir):
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    scheduler = _start_scheduler(port, tmp_path)
    try:
        t0 = time.monotonic()
        status, out, err = cli(
            ["sweep", str(grid), "--scheduler", address, "--wait-workers", "2", "--out", str(tmp_path / "none")], capsys, cache_dir
        )
        assert status == 2 and "has no worker (none joined within 2 s)" in err and err.count("\n") == 1 and out == ""
        assert time.monotonic() - t0 < 20
        assert not (tmp_path / "none").exists()
    finally:
        scheduler.terminate()
        scheduler.wait(timeout=30)


@pytest.mark.slow
def test_a_run_description_field_is_a_grid_axis_by_its_dotted_name(tmp_path, capsys, cache_dir):
    """Dotted names reach the run (the rows equal `loop run --config` with those fields), and
    their values are columns of the results."""
    grid = tmp_path / "grid.toml"
    grid.write_text(TINY.replace("[16.6, 17.0, 17.5]", "17.0") + '"vibrations.scale" = [0.5, 3.0]\n"run.seed" = 3\n')
    out_dir = tmp_path / "out"
    status, _, err = cli(["sweep", str(grid), "--workers", "1", "--out", str(out_dir), "--json"], capsys, cache_dir)
    assert status == 0, err
    rows = list(ResultsTable.read_rows(out_dir / "results.csv").values())
    assert sorted(float(r["vibrations.scale"]) for r in rows) == [0.5, 3.0] and {r["seed"] for r in rows} == {3}
    strehls = set()
    for row in rows:
        description = tmp_path / "run.toml"
        description.write_text(
            f"[star]\nmagnitude_r = 17.0\n[wfs]\nbinning = 4\n[vibrations]\nscale = {row['vibrations.scale']}\n"
            "[run]\noversampling = 1\nwfs_field_arcsec = 0\nduration_s = 0.05\nseed = 3\n"
        )
        status, out, err = cli(["loop", "run", "--config", str(description), "--json"], capsys, cache_dir)
        assert status == 0, err
        assert json.loads(out)["metrics"]["strehl"] == row["strehl"]
        stored = out_dir / "runs" / f"{row['case_id']}.toml"  # the row's own resolved description
        status, out, err = cli(["loop", "run", "--config", str(stored), "--json"], capsys, cache_dir)
        assert status == 0, err
        assert json.loads(out)["metrics"]["strehl"] == row["strehl"]
        strehls.add(row["strehl"])
    assert len(strehls) == 2  # the vibrations' scale changed the run


@pytest.mark.parametrize(
    "text, message",
    [
        ('magnitude = 17.0\n"atmosphere.L0" = 20.0\n', "unknown parameter atmosphere.L0"),
        ('magnitude = 17.0\n"atmosphere.L0_m" = 0.1\n', "L0 must be in 0.5..10000 m"),
        ('magnitude = 17.0\nseeing = 1.0\n"atmosphere.seeing_arcsec" = 0.8\n', "seeing and atmosphere.seeing_arcsec are the same"),
        ('magnitude = 17.0\n"atmosphere.layer" = 1.0\n', "unknown parameter atmosphere.layer"),
    ],
)
def test_bad_dotted_parameters_name_the_problem(text, message, tmp_path):
    with pytest.raises(Exception) as e:
        parse_grid(tomllib.loads(text))
    assert message in str(e.value)


def test_a_dotted_short_name_is_the_short_parameter():
    cases = parse_grid(tomllib.loads('magnitude = 17.0\n"atmosphere.seeing_arcsec" = [0.8, 1.0]\n'))
    assert [c["seeing"] for c in cases] == [0.8, 1.0] and case_id(cases[0]) == case_id({"magnitude": 17.0, "seeing": 0.8})
