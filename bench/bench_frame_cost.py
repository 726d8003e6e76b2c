"""Cost of one sweep case per simulated frame, for every binning and oversampling: the numbers
behind the estimate `soulctl sweep` prints before it starts (soulctl/sweep/estimate.py).

For each binning (the look-up table's sub-apertures and modes; magnitudes 10, 13, 15.5, 17 so
that each is the table's own binning) and oversampling (1 only up to 90 modes), one case is run
as a sweep runs it (``case.run_case`` with its calibration already computed, one thread) at two
durations, twice each; the per-frame cost is the slope of the CPU time of the process (the
least of the two runs) over the frames, the fixed cost per case the intercept (set-up,
metrics).  CPU time, not wall time, so that other work on the machine does not count.  The
calibration is timed cold (empty cache) once, in CPU time too.
Default conditions (seeing 1", noise, vibrations, resonance).
Run:  python bench/bench_frame_cost.py [--frames 100,400] [--out bench/results/frame_cost.json]
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

from soulctl import __version__
from soulctl.files import atomic_write_text
from soulctl.sweep.case import calibrate_case, calibration_setup, observation_for, run_case

MAGNITUDE_OF_BINNING = {1: 10.0, 2: 13.0, 3: 15.5, 4: 17.0}
MAX_MODES_AT_OVERSAMPLING_1 = 90


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", default="100,400")
    p.add_argument("--oversampling", default="1,2,3,4")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "frame_cost.json")
    args = p.parse_args()
    short, long = (int(x) for x in args.frames.split(","))
    rows = []
    with tempfile.TemporaryDirectory() as tmp, threadpool_limits(1):
        for o in (int(x) for x in args.oversampling.split(",")):
            for binning, mag in MAGNITUDE_OF_BINNING.items():
                base = {"magnitude": mag, "binning": binning, "oversampling": o, "seed": 1}
                obs = observation_for(base)
                if o == 1 and obs.modes > MAX_MODES_AT_OVERSAMPLING_1:
                    continue
                t0 = time.process_time()
                cal = calibrate_case(calibration_setup(base), str(Path(tmp) / f"cache-{o}-{binning}"))
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
                rows.append(
                    {
                        "binning": binning,
                        "oversampling": o,
                        "modes": obs.modes,
                        "frame_rate_hz": obs.frame_rate_hz,
                        "frame_ms": 1e3 * per_frame,
                        "case_fixed_s": max(0.0, times[short] - short * per_frame),
                        "calibration_cold_s": cold,
                        "run_s": times,
                    }
                )
    t = Table(title="CPU cost of a sweep case per frame (one thread)")
    for col in ("binning", "oversampling", "modes", "ms/frame", "fixed s/case", "calibration cold [s]"):
        t.add_column(col, justify="right")
    for r in rows:
        t.add_row(
            str(r["binning"]),
            str(r["oversampling"]),
            str(r["modes"]),
            f"{r['frame_ms']:.2f}",
            f"{r['case_fixed_s']:.2f}",
            f"{r['calibration_cold_s']:.1f}",
        )
    Console().print(t)
    result = {
        "benchmark": "frame_cost",
        "soulctl_version": __version__,
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "frames": [short, long],
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
