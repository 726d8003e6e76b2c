"""Cost of one sweep case per simulated frame, for every binning, oversampling and pyramid field
(SOUL's 2.1" with its stop and sensing pupil, 0: the sampled field): the numbers behind the
estimate `soulctl sweep` prints before it starts (soulctl/sweep/estimate.py), and the field's
cost as a ratio, side by side.

For each binning (the look-up table's sub-apertures and modes; magnitudes 10, 13, 15.5, 17 so
that each is the table's own binning) and oversampling (1 only up to 90 modes), one case is run
as a sweep runs it (``case.run_case`` with its calibration already computed, one thread) at two
durations, twice each; the per-frame cost is the slope of the CPU time of the process (the
least of the two runs) over the frames, the fixed cost per case the intercept (set-up,
metrics).  CPU time, not wall time, so that other work on the machine does not count.  The
calibration is timed cold (empty cache) once, in CPU time too.
Default conditions (seeing 1", noise, vibrations, resonance).
Run:  python -m bench.bench_frame_cost [--frames 100,400] [--oversampling 1,2,3,4] [--wfs-field 0,2.1]
      [--out bench/results/frame_cost.json]
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
from threadpoolctl import threadpool_limits

from bench.results_file import provenance
from soulctl import __version__
from soulctl.files import atomic_write_text
from soulctl.sweep.case import calibrate_case, calibration_setup, observation_for, run_case

MAGNITUDE_OF_BINNING = {1: 10.0, 2: 13.0, 3: 15.5, 4: 17.0}
MAX_MODES_AT_OVERSAMPLING_1 = 90


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", default="100,400")
    p.add_argument("--oversampling", default="1,2,3,4")
    p.add_argument("--wfs-field", default="0,2.1", help="pyramid fields of view, arcsec (0: the sampled field)")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "frame_cost.json")
    args = p.parse_args()
    short, long = (int(x) for x in args.frames.split(","))
    fields = [float(x) for x in args.wfs_field.split(",")]
    rows = []
    with tempfile.TemporaryDirectory() as tmp, threadpool_limits(1):
        for o in (int(x) for x in args.oversampling.split(",")):
            for binning, mag in MAGNITUDE_OF_BINNING.items():
                for field in fields:
                    base = {"magnitude": mag, "binning": binning, "oversampling": o, "wfs_field": field, "seed": 1}
                    if o > 1 or observation_for(base).modes <= MAX_MODES_AT_OVERSAMPLING_1:
                        rows.append(measure(base, short, long, Path(tmp) / f"cache-{o}-{binning}-{field:g}"))
    render(rows, fields)
    result = {
        "benchmark": "frame_cost",
        "soulctl_version": __version__,
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "frames": [short, long],
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, json.dumps(result | provenance(), indent=1) + "\n")


def measure(base: dict, short: int, long: int, cache: Path) -> dict:
    """One configuration's per-frame and fixed CPU cost (the least of two runs at each length)
    and its cold calibration."""
    obs = observation_for(base)
    t0 = time.process_time()
    cal = calibrate_case(calibration_setup(base), str(cache))
    cold = time.process_time() - t0
    times = {}
    for frames in (short, long):
        case = {**base, "duration": frames / obs.frame_rate_hz}
        runs = []
        for _ in range(2):
            t0 = time.process_time()
            row = run_case(case, cal)
            runs.append(time.process_time() - t0)
            assert row["status"] == "ok", row["reason"]
        times[frames] = min(runs)
    per_frame = (times[long] - times[short]) / (long - short)
    return {
        "binning": base["binning"],
        "oversampling": base["oversampling"],
        "wfs_field_arcsec": base["wfs_field"],
        "modes": obs.modes,
        "frame_rate_hz": obs.frame_rate_hz,
        "frame_ms": 1e3 * per_frame,
        "case_fixed_s": max(0.0, times[short] - short * per_frame),
        "calibration_cold_s": cold,
        "run_s": times,
    }


def render(rows: list[dict], fields: list[float]) -> None:
    """The table: one line per binning and oversampling, each field's cost side by side and
    the ratio of the last field's per-frame cost to the first's."""
    t = Table(title="CPU cost of a sweep case per frame (one thread); field 0: the sampled field")
    for col in ("binning", "oversampling", "modes"):
        t.add_column(col, justify="right")
    for f in fields:
        for col in ("ms/frame", "fixed s/case", "calibration cold [s]"):
            t.add_column(f'{col}, {f:g}"', justify="right")
    if len(fields) > 1:
        t.add_column(f'ms/frame {fields[-1]:g}" / {fields[0]:g}"', justify="right")
    by = {(r["binning"], r["oversampling"], r["wfs_field_arcsec"]): r for r in rows}
    for b, o in dict.fromkeys((r["binning"], r["oversampling"]) for r in rows):
        cells = [by.get((b, o, f)) for f in fields]
        line = [str(b), str(o), str(next(c for c in cells if c)["modes"])]
        for c in cells:
            line += [f"{c['frame_ms']:.2f}", f"{c['case_fixed_s']:.2f}", f"{c['calibration_cold_s']:.1f}"] if c else ["-"] * 3
        if len(fields) > 1:
            line.append(f"{cells[-1]['frame_ms'] / cells[0]['frame_ms']:.2f}" if cells[0] and cells[-1] else "-")
        t.add_row(*line)
    Console(width=200).print(t)


if __name__ == "__main__":
    main()
