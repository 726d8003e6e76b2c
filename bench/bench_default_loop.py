"""The default loop's speed against the idealised loop's (the fidelity issue: "the speed of the
default loop is within 10 % of today's").

For each paper operating point (R9.7: 40x40 at 1700 Hz; R13: 20x20 at 980 Hz; R16.5: 10x10
at 390 Hz), `loop run`'s own path (``RunConfig.request`` then ``loop.run.run``, seed 1,
seeing 1") in three variants, timed alternately, ``--repeats`` times each:

* ``ideal, gaussian``: the loop when the issue was filed - no OGTL, no NCPA, the Gaussian mirror;
* ``ideal``: the same on the thin-plate mirror (the default mirror since the issue);
* ``default``: every sky-like default - OGTL's probe and lock-in once the loop has closed,
  half the NCPA's reference-slope offsets once k is calibrated, the thin-plate mirror.

The run is long enough for OGTL to act (the loop closes, then two updates, + 0.3 s).  Per
frame: the loop's wall time (closing and run, not the calibration, which is computed into the
cache before the timed runs) over its frames, and the median and 99th percentile of the single
frames.  The ratio is the median over repeats of the variant's ms per frame over the
``ideal, gaussian`` one's.
Run:  python -m bench.bench_default_loop [--cases R9.7,R13,R16.5] [--repeats 2] [--out bench/results/default_loop.json]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from bench.results_file import save
from soulctl.cli.common import default_cache_dir
from soulctl.cli.loop import IDEAL
from soulctl.loop.optimisers import LiveOptimisers
from soulctl.loop.run import calibration_for, run
from soulctl.optics.cache import ArrayCache
from soulctl.run_config import read_run_config

EXAMPLES = Path(__file__).parents[1] / "examples"
CASES = {"R9.7": "paper_r9.7_1700hz.toml", "R13": "paper_r13_980hz.toml", "R16.5": "paper_r16.5_390hz.toml"}
VARIANTS = {
    "ideal, gaussian": IDEAL | {"mirror.influence": "gaussian"},
    "ideal": IDEAL,
    "default": {},
}


def descriptions(case: str) -> dict:
    """The case's run description per variant, lasting long enough for OGTL to act."""
    base = read_run_config(EXAMPLES / CASES[case])
    obs = base.observation
    need = LiveOptimisers(False, True, None, base.auxiliary.probe()).frames_needed(obs)
    duration = math.ceil((need / obs.frame_rate_hz + 0.3) * 10) / 10
    return {name: base.with_values(values | {"run.duration_s": duration, "run.seed": 1}).resolved() for name, values in VARIANTS.items()}


def timed(description, cache: ArrayCache) -> dict:
    """One run's wall time per frame (median, p99 of single frames, mean)."""
    request = description.request()
    aux = description.auxiliary.live()
    ends: list[float] = []
    t0 = time.perf_counter()
    result = run(request, cache, progress=lambda _, e=ends: e.append(time.perf_counter()), aux=aux)
    frame_ms = np.diff([t0 + result.calibration_seconds] + ends) * 1e3
    return {
        "frames": request.frames,
        "ms_per_frame": result.seconds / request.frames * 1e3,
        "frame_ms_median": float(np.median(frame_ms[1:])),
        "frame_ms_p99": float(np.percentile(frame_ms[1:], 99)),
        "ogtl": bool(aux is not None and aux.ogtl),
        "strehl": None if result.metrics is None else float(result.metrics.strehl),
    }


def bench_case(case: str, repeats: int, cache: ArrayCache) -> list[dict]:
    """The variants of one case, timed alternately (each variant's calibration computed into the cache first)."""
    ds = descriptions(case)
    for d in ds.values():
        calibration_for(d.request(), cache)
    runs: dict[str, list[dict]] = {name: [] for name in ds}
    for _ in range(repeats):
        for name, d in ds.items():
            runs[name].append(timed(d, cache))
            print(case, name, json.dumps(runs[name][-1]), flush=True)
    ref = float(np.median([r["ms_per_frame"] for r in runs["ideal, gaussian"]]))
    rows = []
    for name, rs in runs.items():
        ms = float(np.median([r["ms_per_frame"] for r in rs]))
        rows.append({"case": case, "variant": name, "ms_per_frame": ms, "ratio": ms / ref, "runs": rs})
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", default=",".join(CASES))
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "default_loop.json")
    args = p.parse_args()
    cache = ArrayCache(default_cache_dir())
    rows = [row for case in args.cases.split(",") for row in bench_case(case, args.repeats, cache)]
    t = Table(title=f"Default loop against the idealised one, ms per frame ({args.repeats} runs each, alternated)", title_justify="left")
    for col in ("case", "variant", "frames", "OGTL", "ms/frame (runs)", "frame median/p99", "ratio", "Strehl"):
        t.add_column(col, justify="left" if col in ("case", "variant") else "right")
    for r in rows:
        rs = r["runs"]
        t.add_row(
            r["case"],
            r["variant"],
            str(rs[0]["frames"]),
            "on" if rs[0]["ogtl"] else "off",
            " / ".join(f"{x['ms_per_frame']:.2f}" for x in rs),
            f"{np.median([x['frame_ms_median'] for x in rs]):.2f} / {np.median([x['frame_ms_p99'] for x in rs]):.2f}",
            f"{r['ratio']:.3f}",
            " / ".join(f"{x['strehl']:.3f}" if x["strehl"] is not None else "-" for x in rs),
        )
    console = Console(width=200)
    console.print(t)
    save(args.out, {"benchmark": "default_loop", "numpy": np.__version__, "rows": rows}, console)


if __name__ == "__main__":
    main()
