"""Benchmark of the Tip/Tilt IIR design (soulctl filter design) and of the loop analysis.

Cases, run side by side in one process:
  design <rate>     design_tt_filter(rate) with the command's defaults, one run per seed
                    (--seeds, default 1..3): wall and CPU time (the design's BLAS runs on
                    one thread, so CPU ~ wall), cost evaluations, evaluations per second,
                    and whether the seeds agree on the filter (same optimum).
  analyze           soulctl.control.transfer.analyze of the paper's 1700 Hz IIR loop
                    (--repeat calls): median and p99 per call.
Target (issue 3): <= 60 s per frame rate on 2 cores.

Run:  python -m bench.bench_design [--rates 1700,1350,1000,750] [--seeds 3] [--out bench/results/design.json]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from bench.results_file import save
from soulctl import tables
from soulctl.control.delay import DelayModel
from soulctl.control.design import design_tt_filter
from soulctl.control.filters import Filter
from soulctl.control.transfer import Loop, Plant, analyze

TARGET_S = 60.0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rates", default="1700,1350,1000,750")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--repeat", type=int, default=200)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "design.json")
    args = p.parse_args()

    rows = []
    for rate in (float(r) for r in args.rates.split(",")):
        runs = []
        for seed in range(1, args.seeds + 1):
            t0, c0 = time.perf_counter(), time.process_time()
            r = design_tt_filter(rate, seed=seed)
            runs.append(
                {
                    "seed": seed,
                    "wall_s": time.perf_counter() - t0,
                    "cpu_s": time.process_time() - c0,
                    "evaluations": r.evaluations,
                    "cost_mas2": r.iir.cost_mas2,
                    "rejection_ratio": r.rejection_ratio,
                    "zeros": [z.real for z in r.iir.filter.zeros],
                    "poles": [q.real for q in r.iir.filter.poles],
                    "gain": r.iir.filter.gain,
                }
            )
        walls = np.array([x["wall_s"] for x in runs])
        costs = np.array([x["cost_mas2"] for x in runs])
        rows.append(
            {
                "rate_hz": rate,
                "runs": runs,
                "median_s": float(np.median(walls)),
                "max_s": float(walls.max()),
                "median_cpu_s": float(np.median([x["cpu_s"] for x in runs])),
                "evaluations_per_s": float(np.median([x["evaluations"] / x["wall_s"] for x in runs])),
                "cost_spread": float((costs.max() - costs.min()) / costs.min()),
                "meets_target": bool(walls.max() <= TARGET_S),
            }
        )

    roots = {r.frame_rate_hz: r for r in tables.tt_iir_table()}[1700]
    loop = Loop(Filter.iir(roots.zeros, roots.poles, 0.69), Plant(DelayModel.from_table().frames(1700)), 1700.0)
    analyze(loop)
    times = []
    for _ in range(args.repeat):
        t0 = time.perf_counter_ns()
        analyze(loop)
        times.append((time.perf_counter_ns() - t0) / 1e6)
    analysis = {"median_ms": float(np.median(times)), "p99_ms": float(np.percentile(times, 99)), "calls": args.repeat}

    t = Table(title=f"Tip/Tilt IIR design, {args.seeds} seeds per rate (target <= {TARGET_S:g} s per rate)")
    for c in ("rate", "median s", "max s", "median CPU s", "evals/s", "cost spread over seeds", "target"):
        t.add_column(c, justify="right")
    for r in rows:
        t.add_row(
            f"{r['rate_hz']:g} Hz",
            f"{r['median_s']:.1f}",
            f"{r['max_s']:.1f}",
            f"{r['median_cpu_s']:.1f}",
            f"{r['evaluations_per_s']:.0f}",
            f"{100 * r['cost_spread']:.2f} %",
            "met" if r["meets_target"] else "MISSED",
        )
    console = Console()
    console.print(t)
    console.print(
        f"analyze(): median {analysis['median_ms']:.2f} ms, p99 {analysis['p99_ms']:.2f} ms "
        f"(p99/median {analysis['p99_ms'] / analysis['median_ms']:.2f}) over {args.repeat} calls"
    )
    save(args.out, {"design": rows, "analyze": analysis}, console)


if __name__ == "__main__":
    main()
