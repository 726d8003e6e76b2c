"""MGM's low-order gains at the paper's R13 case (issue: MGM and OGTL that never drive the
loop unstable): the case that lost 0.055 (R13, 20x20, 980 Hz, FeII, 1.0", 5 m/s, seed 2, MGM
with OGTL, default options) is optimised, then its final gains are evaluated on the same
screens with only modes 3-10 scaled, and with the initial gains at the final k.  Not in CI
(~10 min on one core).

Run:  python -m validation.r13_low_order_scan [--seed 2] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from soulctl.cli.common import default_cache_dir
from soulctl.files import atomic_write_text
from soulctl.loop.evaluation import evaluate
from soulctl.loop.optimize import optimize
from soulctl.loop.run import calibration_for
from soulctl.loop.schedule import OptimizeRequest
from soulctl.optics.cache import ArrayCache
from soulctl.run_config import RunConfig
from validation.faint_cases import NO_NCPA, R13_NIGHT  # noqa: E402
from validation.gain_optimisation import observation  # noqa: E402
from validation.provenance import provenance

SCALES = (1.25, 1.5, 1.75)
LOW = slice(2, 10)  # modes 3-10


def scanned_gains(initial: np.ndarray, final: np.ndarray, k_before: float, k_after: float) -> dict[str, np.ndarray]:
    """MGM's final gains, those with modes 3-10 scaled, with modes 3-30 at the initial g k, and
    the initial gains at the final k (their g k as *before*)."""
    cases = {"final": final}
    for f in SCALES:
        g = final.copy()
        g[LOW] *= f
        cases[f"modes 3-10 x {f:g}"] = g
    g = final.copy()
    g[2:30] = initial[2:30] * k_before / k_after
    cases["modes 3-30 at the initial g k"] = g
    cases["initial at the final k"] = initial * k_before / k_after
    return cases


def r13_case(seed: int):
    """The paper's R13 case (20x20, 980 Hz, FeII, 1.0", 5 m/s, no NCPA) optimised by MGM with
    1 s measurements: its OptimizeRequest (whose session length sets the screens), the cache,
    the calibration and the design gains."""
    run = RunConfig(observation=observation(13.0, 980.0), atmosphere=R13_NIGHT, band="FeII", seed=seed, ncpa=NO_NCPA).request()
    cache = ArrayCache(default_cache_dir())
    return OptimizeRequest(run=run, method="mgm", measure_s=1.0), cache, calibration_for(run, cache), run.design_gains()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=2)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "r13_low_order_scan.json")
    a = p.parse_args()
    request, cache, cal, design = r13_case(a.seed)
    r = optimize(request, cache)
    assert r.before is not None and r.after is not None, r.failure()
    k_before, k_after = r.sensitivities
    out = {"seed": a.seed, **provenance(), "k": [k_before, k_after], "before": list(r.before.window_strehls)}
    out["after"] = list(r.after.window_strehls)
    out["scan"] = {}
    for name, gains in scanned_gains(r.initial_gains, r.gains, k_before, k_after).items():
        windows = evaluate(request, cal, design, gains, k_after).window_strehls
        low_gk = float(np.mean(gains[LOW]) * k_after)
        out["scan"][name] = {"windows": list(windows), "mean": float(np.mean(windows)), "low_order_gk": low_gk}
        print(f"{name:32s} {np.mean(windows):.4f} {np.round(windows, 3)}", flush=True)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(a.out, json.dumps(out, indent=1, default=float))


if __name__ == "__main__":
    main()
