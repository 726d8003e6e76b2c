"""Benchmark of the mis-registration verdict (`loop run --misregistration`: the eigenmodes of
R D', ``control.coupling``) against the loop it judges.

Cases, side by side in one process, per configuration (the paper's R9.7, R13 and R16.5 rows):
  D'        ``optics.calibration.moved_mirror_response`` computed (push-pull of every mode
            through the moved mirror, no cache; --repeat runs): median and the maximum.
  verdict   ``loop.run.registration_stability`` as a repeated run sees it (D' and the
            optical-gain table from the cache, which the first call fills; the eigenvalues,
            poles and margin): median and the maximum of the repeats.
  loop      ``loop.run.run`` of the registered loop for --duration s: wall time, and what a
            first run with a new mis-registration adds (D' + verdict) as a fraction of it.
Peak RSS of the process at the end (the verdict keeps one n_slopes x n_modes matrix).

Run:  python -m bench.bench_misregistration [--cases R9.7,R13,R16.5] [--repeat 3] [--duration 1]
          [--out bench/results/misregistration.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import resource
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from bench.results_file import save
from soulctl.cli.common import default_cache_dir
from soulctl.loop.run import calibration_for, closed_loop_for, registration_stability, run
from soulctl.optics.cache import ArrayCache
from soulctl.optics.calibration import moved_mirror_response
from soulctl.optics.registration import Misregistration
from soulctl.run_config import RunConfig

CASES = {"R9.7": (9.7, "H"), "R13": (13.0, "FeII"), "R16.5": (16.5, "Ks")}
SHIFT = Misregistration(shift_x_pitch=0.5)


def timed(fun, repeat: int) -> tuple[float, float]:
    """(median, maximum) wall time of ``fun()`` in s."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fun()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), float(np.max(times))


def case_row(label: str, repeat: int, duration: float, cache: ArrayCache) -> dict:
    mag, band = CASES[label]
    config = RunConfig().with_values({"star.magnitude_r": mag, "run.band": band, "ncpa.rms_nm": 0.0, "run.duration_s": duration})
    request = config.request()
    obs = request.observation
    cal = calibration_for(request, cache)
    structure = request.sampled_structure()
    gains = request.design_gains()
    moved = dataclasses.replace(request, misregistration=SHIFT)

    loop = closed_loop_for(moved, cal, gains, structure)  # the verdict reads its gains, k and R

    def verdict():
        return registration_stability(moved, cal, loop, gains.forgetting, structure, cache)

    verdict()  # fills the cache: chi table and D'
    d_median, d_max = timed(lambda: moved_mirror_response(cal, SHIFT), repeat)
    v_median, v_max = timed(verdict, repeat)
    t0 = time.perf_counter()
    run(request, cache)
    loop_s = time.perf_counter() - t0
    return {
        "case": label,
        "modes": obs.modes,
        "slopes": int(cal.interaction_matrix.shape[0]),
        "frame_rate_hz": obs.frame_rate_hz,
        "d_prime_median_s": d_median,
        "d_prime_max_s": d_max,
        "verdict_median_s": v_median,  # D' and chi from the cache
        "verdict_max_s": v_max,
        "loop_s": loop_s,
        "loop_duration_s": duration,
        "first_run_over_loop": (d_median + v_median) / loop_s,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cases", default="R9.7,R13,R16.5")
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--duration", type=float, default=1.0)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "misregistration.json")
    a = p.parse_args()
    cache = ArrayCache(default_cache_dir())
    rows = [case_row(label, a.repeat, a.duration, cache) for label in a.cases.split(",")]
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    t = Table(title=f"Mis-registration verdict (shift {SHIFT.shift_x_pitch} pitch) against the loop, {a.repeat} repeats")
    columns = ("case", "modes", "D' computed: median / max s", "verdict, D' cached: median / max s", f"loop {a.duration:g} s: wall s")
    for c in (*columns, "first run: (D' + verdict) / loop"):
        t.add_column(c, justify="right")
    for r in rows:
        t.add_row(
            r["case"],
            str(r["modes"]),
            f"{r['d_prime_median_s']:.2f} / {r['d_prime_max_s']:.2f}",
            f"{r['verdict_median_s']:.2f} / {r['verdict_max_s']:.2f}",
            f"{r['loop_s']:.1f}",
            f"{r['first_run_over_loop']:.2f}",
        )
    console = Console()
    console.print(t)
    console.print(f"peak RSS {rss_mb:.0f} MB")
    save(a.out, {"rows": rows, "peak_rss_mb": rss_mb}, console)


if __name__ == "__main__":
    main()
