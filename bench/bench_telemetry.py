"""Benchmark of telemetry at constant memory: peak RSS and loop speed of `soulctl loop run`
against the simulated duration, with and without --telemetry, with --mgm --ogtl.

Each case is one `soulctl loop run` process (peak RSS from wait4's ru_maxrss, loop speed
from the command's own frames_per_second), run side by side in one invocation:

  for each configuration (--mags; R9.7: 40x40, 500 modes, 1700 Hz; R16.5: 10x10, 90 modes,
  250 Hz) and each duration (--durations, s): without telemetry, with --telemetry (default
  fields), with --telemetry --telemetry-fields all; every case with --mgm --ogtl unless
  --no-aux (they need the duration to hold the closing and two update periods).
Reported: peak RSS (MB), its slope against simulated time (MB per simulated second, least
squares over the durations), frames per second, and the telemetry's cost in loop speed
(frames/s with against without, same duration).  Targets (issue 17): slope <= 20 MB/s;
a 600 s run under 2 GB; telemetry costs <= 5 % of loop speed.

Run:  python -m bench.bench_telemetry [--mags 9.7,16.5] [--durations 0.25,1,5] [--out bench/results/telemetry.json]
      (a 600 s run at R16.5: --mags 16.5 --durations 600)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from bench.results_file import provenance
from soulctl import __version__
from soulctl.files import atomic_write_text

MODES = {
    "none": [],
    "telemetry": ["--telemetry", "{dir}/t.h5"],
    "telemetry all": ["--telemetry", "{dir}/t.h5", "--telemetry-fields", "all"],
}


def run_case(mag: str, duration: float, mode: str, aux: bool) -> dict:
    """One `loop run` process: peak RSS (MB), frames/s, wall time, file size (MB)."""
    with tempfile.TemporaryDirectory() as d:
        extra = [a.format(dir=d) for a in MODES[mode]]
        cmd = [sys.executable, "-m", "soulctl.cli.app", "loop", "run", "--mag", mag, "--duration", str(duration)]
        cmd += [*(["--mgm", "--ogtl"] if aux else []), "--json", *extra]
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, cwd=d)  # the installed soulctl, not ./soulctl
        out = proc.stdout.read() if proc.stdout else b""
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        size = os.path.getsize(Path(d) / "t.h5") / 2**20 if extra else 0.0
    result = json.loads(out) if out else {}
    return {
        "mag": mag,
        "duration_s": duration,
        "mode": mode,
        "aux": aux,
        "exit_status": os.waitstatus_to_exitcode(status),
        "peak_rss_mb": usage.ru_maxrss / 1024,
        "frames_per_second": result.get("frames_per_second"),
        "wall_s": wall,
        "file_mb": size,
    }


def writer_cost(n_slopes: int, n_modes: int = 500, n_actuators: int = 672, frames: int = 4096) -> list[dict]:
    """Seconds per frame of ``Hdf5Writer.append`` (buffering, chunk compression and flushes
    included) at 40x40's sizes, in this process: default fields and all fields.  Robust to
    other load, unlike the loop-speed ratio: it is the cost itself."""
    from soulctl.telemetry.schema import DEFAULT_FIELDS, PER_FRAME
    from soulctl.telemetry.stream import Hdf5Writer

    rng = np.random.default_rng(1)
    sizes = {"slopes": n_slopes, "commands": n_actuators}
    values = {name: rng.normal(size=sizes.get(name, n_modes)).astype(np.float32) for name in PER_FRAME if name not in SCALARS}
    values |= {name: float(rng.normal()) for name in SCALARS}
    out = []
    for label, fields in (("default fields", DEFAULT_FIELDS), ("all fields", PER_FRAME)):
        with tempfile.TemporaryDirectory() as d:
            w = Hdf5Writer(Path(d) / "w.h5", fields, 1)
            w.describe({"rate_hz": 1700.0, "delay_frames": 2.0, "n_modes": n_modes}, {})
            times = np.empty(frames)
            for k in range(frames):
                t0 = time.perf_counter()
                w.append(k, values)
                times[k] = time.perf_counter() - t0
            w.abandon()
        out.append(
            {"fields": label, "mean_ms": 1e3 * times.mean(), "median_ms": 1e3 * np.median(times), "p99_ms": 1e3 * np.percentile(times, 99)}
        )
    return out


SCALARS = ("residual_rms_nm", "sensitivity", "flux")


def slope(rows: list[dict]) -> float | None:
    """Least-squares slope of peak RSS (MB) against simulated seconds."""
    if len({r["duration_s"] for r in rows}) < 2:
        return None
    x = np.array([r["duration_s"] for r in rows])
    y = np.array([r["peak_rss_mb"] for r in rows])
    return float(np.polyfit(x, y, 1)[0])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mags", default="9.7,16.5")
    p.add_argument("--durations", default="0.25,1,5")
    p.add_argument("--modes", default=",".join(MODES))
    p.add_argument("--writer-only", action="store_true", help="only the writer's cost per frame (in-process, seconds)")
    p.add_argument("--slopes", type=int, default=2568, help="slopes per frame for the writer cost (40x40: 1284 sub-apertures)")
    p.add_argument("--no-aux", action="store_true", help="without --mgm --ogtl (they need at least closing + two periods)")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "telemetry.json")
    args = p.parse_args()
    console = Console()
    cost = writer_cost(args.slopes)
    w = Table(title=f"Hdf5Writer.append per frame at 40x40 ({args.slopes} slopes, 500 modes, 672 actuators)")
    for c in ("fields", "mean [ms]", "median [ms]", "p99 [ms]"):
        w.add_column(c, justify="right")
    for r in cost:
        w.add_row(r["fields"], f"{r['mean_ms']:.3f}", f"{r['median_ms']:.3f}", f"{r['p99_ms']:.3f}")
    console.print(w)
    if args.writer_only:
        atomic_write_text(args.out, json.dumps({"writer_cost": cost} | provenance(), indent=1))
        return
    rows = []
    for mag in args.mags.split(","):
        for duration in (float(d) for d in args.durations.split(",")):
            for mode in args.modes.split(","):
                rows.append(run_case(mag, duration, mode, not args.no_aux))
                print(json.dumps(rows[-1]), file=sys.stderr)
    t = Table(title=f"loop run{'' if args.no_aux else ' --mgm --ogtl'}: peak RSS and speed against simulated time")
    for c in ("R mag", "duration [s]", "telemetry", "peak RSS [MB]", "frames/s", "speed vs none", "file [MB]", "exit"):
        t.add_column(c, justify="right")
    for r in rows:
        base = next((b for b in rows if b["mag"] == r["mag"] and b["duration_s"] == r["duration_s"] and b["mode"] == "none"), None)
        ratio = (
            r["frames_per_second"] / base["frames_per_second"] if base and base["frames_per_second"] and r["frames_per_second"] else None
        )
        r["speed_vs_none"] = ratio
        t.add_row(
            r["mag"],
            f"{r['duration_s']:g}",
            r["mode"],
            f"{r['peak_rss_mb']:.0f}",
            f"{r['frames_per_second'] or 0:.1f}",
            "-" if ratio is None else f"{ratio:.3f}",
            f"{r['file_mb']:.1f}",
            str(r["exit_status"]),
        )
    console.print(t)
    slopes = {
        f"{m} {mode}": slope([r for r in rows if r["mag"] == m and r["mode"] == mode])
        for m in args.mags.split(",")
        for mode in args.modes.split(",")
    }
    s = Table(title="peak RSS slope [MB per simulated second] (target <= 20)")
    s.add_column("case")
    s.add_column("slope", justify="right")
    for k, v in slopes.items():
        s.add_row(k, "-" if v is None else f"{v:.2f}")
    console.print(s)
    report = {
        "soulctl": __version__,
        "machine": platform.platform(),
        "cpus": os.cpu_count(),
        "writer_cost": cost,
        "rows": rows,
        "rss_slope_mb_per_s": slopes,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, json.dumps(report | provenance(), indent=1))


if __name__ == "__main__":
    main()
