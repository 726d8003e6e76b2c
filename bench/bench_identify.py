"""Benchmark of `soulctl telemetry identify` and `soulctl rtc check` (issue targets: identify
on 60 s of 500-mode telemetry at 1700 Hz within 10 s on the 2-core machine; rtc check of a
500-mode parameter set within 2 s).

The telemetry: a short R9.7 run (40x40, 500 modes, 1700 Hz, default fields) simulated once,
its measured and command modes tiled in time to each duration (--durations) with the run's
description, so that the identification reads and fits exactly the data sizes of a real
record (its cost does not depend on the values).  Each case is one `soulctl` process: wall
time of the command, its own per-stage times (identify's JSON) and peak RSS (wait4), side by
side for the durations; rtc check on the same configuration's 500 modes, median and p99 of
--repeat runs, with a gain file and with a whole RTC description (npz).

Run:  python -m bench.bench_identify [--durations 10,30,60] [--repeat 5] [--out bench/results/identify.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from bench.results_file import provenance
from soulctl import __version__
from soulctl.control.gains import LoopGains, mode_filters
from soulctl.control.rtc import build_rtc
from soulctl.files import atomic_write_text
from soulctl.telemetry.formats import open_telemetry
from soulctl.telemetry.hdf5 import write_telemetry

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "paper_r9.7_1700hz.toml"


def timed(cmd: list[str], cwd: Path) -> tuple[float, float, str]:
    """(wall s, peak RSS MB, stdout) of one process."""
    t0 = time.perf_counter()
    with tempfile.TemporaryFile() as out:
        proc = subprocess.Popen(cmd, cwd=cwd, stdout=out, stderr=subprocess.DEVNULL)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        if os.waitstatus_to_exitcode(status) != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed")
        out.seek(0)
        return wall, usage.ru_maxrss / 1024.0, out.read().decode()


def base_record(work: Path, seconds: float) -> Path:
    path = work / "base.h5"
    cmd = ["soulctl", "loop", "run", "--config", str(EXAMPLE), "--duration", str(seconds), "--telemetry", str(path)]
    subprocess.run(cmd, cwd=work, check=True, capture_output=True)
    return path


def tiled(base: Path, seconds: float, work: Path) -> Path:
    """The base record's modes repeated to ``seconds`` (the run description kept)."""
    with open_telemetry(base, ()) as tm:
        rate = tm.attribute("rate_hz")
        m, c = tm.read("measured_modes"), tm.read("command_modes")
        attributes = {k: tm.attribute(k) for k in ("rate_hz", "delay_frames", "n_modes")}
        attributes["run_description"] = tm.attribute("run_description")
        configuration = tm.configuration()
        gains = tm.read("gains")
    frames = int(seconds * rate)
    reps = -(-frames // len(m))
    arrays = {
        "measured_modes": np.tile(m, (reps, 1))[:frames],
        "command_modes": np.tile(c, (reps, 1))[:frames],
        "gains": gains,
        "frame_counter": np.arange(frames),
    }
    path = work / f"tiled_{seconds:g}s.h5"
    write_telemetry(path, arrays, attributes, configuration, immediate=True)
    return path


def rtc_cases(work: Path, config: Path) -> dict[str, Path]:
    from soulctl.run_config import read_run_config

    obs = read_run_config(config).observation
    gains = LoopGains(0.6, 0.4, 0.3).per_mode(obs.modes)
    gain_file = work / "gains.toml"
    gain_file.write_text("gains = [" + ", ".join(map(str, gains)) + "]\n")
    rng = np.random.default_rng(1)
    R, M = rng.standard_normal((obs.modes, 6400)), rng.standard_normal((672, obs.modes))
    m = build_rtc(mode_filters(obs, LoopGains(0.6, 0.4, 0.3), obs.modes), R, M)
    npz = work / "rtc.npz"
    np.savez(npz, Lambda=m.Lambda, Delta=m.Delta, Xi=m.Xi, Sigma=m.Sigma, R=R, M=M)
    return {"gain file": gain_file, "RTC description (npz, 6400 slopes)": npz}


def in_process_check(params: Path, config: Path) -> float:
    """Seconds of the check itself (reading, rebuilding, margins of every mode), no start-up."""
    from soulctl.control.check import Criteria, check_modes
    from soulctl.control.gains import read_gain_file
    from soulctl.control.rtc_file import compare, is_rtc_file, read_rtc_file
    from soulctl.control.structure import sampled_structure
    from soulctl.run_config import read_run_config

    t0 = time.perf_counter()
    description = read_run_config(config)
    obs = description.observation
    if is_rtc_file(params):
        unit = mode_filters(obs, LoopGains(1.0, 1.0, 1.0), obs.modes)
        gains = compare(read_rtc_file(params), unit).gains
    else:
        gains = read_gain_file(params)
    filters = mode_filters(obs, LoopGains.from_modes(gains), obs.modes)
    structure = sampled_structure(description.structure, obs.frame_rate_hz)
    ba = None if structure is None else structure.coefficients(obs.frame_rate_hz)
    check_modes(filters, np.ones(obs.modes), obs.delay_frames, obs.frame_rate_hz, ba, Criteria())
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--durations", default="10,30,60")
    ap.add_argument("--base-seconds", type=float, default=2.0)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "identify.json"))
    args = ap.parse_args()
    console = Console()
    rows, rtc_rows = [], []
    with tempfile.TemporaryDirectory() as d:
        work = Path(d)
        base = base_record(work, args.base_seconds)
        config = work / "run.toml"
        config.write_text(
            subprocess.run(
                ["soulctl", "loop", "run", "--config", str(EXAMPLE), "--print-config"], capture_output=True, text=True, check=True
            ).stdout
        )
        for seconds in (float(x) for x in args.durations.split(",")):
            path = tiled(base, seconds, work)
            wall, rss, out = timed(["soulctl", "telemetry", "identify", str(path), "--json"], work)
            stages = json.loads(out)["seconds"]
            rows.append(
                {"seconds": seconds, "file_mb": path.stat().st_size / 2**20, "wall_s": wall, "peak_rss_mb": rss, "stages_s": stages}
            )
            path.unlink()
        startup = [timed(["soulctl", "--version"], work)[0] for _ in range(args.repeat)]
        for name, params in rtc_cases(work, config).items():
            cmd = ["soulctl", "rtc", "check", str(params), "--config", str(config), "--json"]
            walls = [timed(cmd, work)[0] for _ in range(args.repeat)]
            inside = [in_process_check(params, config) for _ in range(args.repeat)]
            rtc_rows.append({
                "params": name, "median_s": float(np.median(walls)), "p99_s": float(np.percentile(walls, 99)),
                "in_process_median_s": float(np.median(inside)), "startup_median_s": float(np.median(startup)), "runs": args.repeat,
            })  # fmt: skip
    t = Table(title="telemetry identify, R9.7 500 modes 1700 Hz (wall time of the command, stage times cumulative)")
    for col in ("record [s]", "file [MB]", "wall [s]", "read [s]", "delay+chi [s]", "lines [s]", "r0/L0 [s]", "peak RSS [MB]"):
        t.add_column(col, justify="right")
    for r in rows:
        s = r["stages_s"]
        t.add_row(f"{r['seconds']:g}", f"{r['file_mb']:.0f}", f"{r['wall_s']:.2f}", f"{s['read']:.2f}", f"{s['delay_and_gains']:.2f}",
                  f"{s['vibrations']:.2f}", f"{s['turbulence']:.2f}", f"{r['peak_rss_mb']:.0f}")  # fmt: skip
    console.print(t)
    t = Table(title=f"rtc check, 500 modes ({args.repeat} runs of the command)")
    for col in ("parameters", "command median [s]", "p99 [s]", "in-process median [s]", "soulctl --version [s]"):
        t.add_column(col, justify="right")
    for r in rtc_rows:
        t.add_row(
            r["params"], f"{r['median_s']:.2f}", f"{r['p99_s']:.2f}", f"{r['in_process_median_s']:.3f}", f"{r['startup_median_s']:.2f}"
        )
    console.print(t)
    report = {
        "soulctl": __version__,
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "identify": rows,
        "rtc_check": rtc_rows,
    }
    atomic_write_text(args.out, json.dumps(report | provenance(), indent=1))


if __name__ == "__main__":
    main()
