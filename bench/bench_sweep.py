"""Scaling of `soulctl sweep`: wall time of one 16-case grid with 1 and 2 local Dask workers.

Grid: 4 magnitudes (16.0, 16.5, 17.0, 17.5) x 2 seeings (0.8, 1.2") x 2 seeds, the look-up
table's configurations (13x13 and 10x10 sub-apertures, 90 and 54 modes), 40-px pupil
(oversampling 1), 0.5 s of loop each.  The calibrations are computed cold in a fresh cache for
each worker count (the sweep computes each distinct one once, as a task).
Reported per worker count: wall time (cluster start-up included), the sum of
the cases' own run times, the speed-up over 1 worker and the parallel efficiency.
Run:  python -m bench.bench_sweep [--workers 1,2] [--out bench/results/sweep.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table

from bench.results_file import provenance
from soulctl import __version__
from soulctl.files import atomic_write_text
from soulctl.sweep.grid import parse_grid
from soulctl.sweep.runner import run_sweep

GRID = {"magnitude": [16.0, 16.5, 17.0, 17.5], "seeing": [0.8, 1.2], "seed": [1, 2], "oversampling": 1, "duration": 0.5}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--workers", default="1,2")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "sweep.json")
    args = p.parse_args()
    cases = parse_grid(GRID)
    rows = []
    for n in [int(w) for w in args.workers.split(",")]:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            report = run_sweep(cases, Path(tmp), workers=n, cache_dir=str(Path(tmp) / "cache"))
            wall = time.perf_counter() - t0
        case_seconds = sum(r["run_seconds"] for r in report.rows)
        rows.append({"workers": n, "cases": len(cases), "wall_s": wall, "case_seconds_sum": case_seconds, "failed": report.failed})
    base = rows[0]["wall_s"]
    for r in rows:
        r["speedup"] = base / r["wall_s"]
        r["efficiency"] = r["speedup"] / (r["workers"] / rows[0]["workers"])
    t = Table(title=f"sweep scaling: {len(cases)} cases, 0.5 s each, 13x13/10x10 sub-apertures, 40-px pupil")
    for col in ("workers", "wall [s]", "sum of case run times [s]", "speed-up", "efficiency", "failed"):
        t.add_column(col, justify="right")
    for r in rows:
        t.add_row(
            str(r["workers"]),
            f"{r['wall_s']:.1f}",
            f"{r['case_seconds_sum']:.1f}",
            f"{r['speedup']:.2f}",
            f"{r['efficiency']:.2f}",
            str(r["failed"]),
        )
    Console().print(t)
    result = {
        "benchmark": "sweep",
        "soulctl_version": __version__,
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "grid": GRID,
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, json.dumps(result | provenance(), indent=1) + "\n")


if __name__ == "__main__":
    main()
