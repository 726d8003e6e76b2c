"""The R9.4 night at 1.5" (seed 3): is MGM's loss in the paired evaluation its gains or the k
that OGTL reaches with them? (issue: gain optimisation at every operating point; not in CI:
~40 min on one core.)

`validation/paper_nights.py` found MGM's gains losing 0.040 +- 0.016 in Strehl there, with
the evaluation's OGTL ending at k = 4.76 (*before*) and 5.02 (*after*).  This script runs the
same night and seed once more (`optimize gains`'s defaults, the night's conditions), then
evaluates on the run's own turbulence and noise, each loop closed afresh (the paired
evaluation, `soulctl.loop.optimize.evaluate`):

- ``ogtl``: *before* and *after* as `optimize gains` judges them, OGTL running from k = 1;
- ``tt_after`` / ``high_after``: OGTL running, MGM's gains for Tip/Tilt only (the rest the
  initial), or for the other modes only;
- ``fixed k``: *before* and *after* at one fixed k (and the NCPA offsets applied), for each
  of the two k the OGTL evaluations ended at.

If MGM's gains lose at one fixed k as much as with OGTL, the gains do it; if they lose only
with OGTL, it is the k that OGTL reaches with them.  Every evaluation is the mean of the
windows' Strehl ratios (4 windows of 1 s, FeII), paired with the *before* of its own kind.

Run:  python -m validation.r94_split [--night R9.4] [--seed 3] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np

from soulctl.cli.common import default_cache_dir
from soulctl.control.gains import TIP_TILT
from soulctl.loop.evaluation import evaluate
from soulctl.loop.optimisers import ogtl_task
from soulctl.loop.optimize import optimize
from soulctl.loop.run import calibration_for
from soulctl.loop.schedule import OptimizeRequest
from soulctl.optics.cache import ArrayCache
from validation.paper_nights import NIGHTS, night_request  # noqa: E402
from validation.provenance import code_fingerprint, provenance

RESULTS = Path(__file__).parent / "results"


def summary(m) -> dict:
    return {
        "strehl": m.strehl,
        "windows": m.window_strehls,
        "k_end": m.sensitivity,
        "residual_nm": m.residual_nm,
        "tt_jitter_mas": m.tt_jitter_mas,
    }


def paired(after: dict, before: dict) -> list[float]:
    """after - before over the windows: mean and standard error."""
    d = np.subtract(after["windows"], before["windows"])
    return [float(d.mean()), float(d.std(ddof=1) / math.sqrt(d.size))]


def split(request: OptimizeRequest, cache: ArrayCache, result) -> dict:
    """The evaluations of the module docstring on ``result``'s run."""
    cal = calibration_for(request.run, cache)
    design = request.run.design_gains()
    noise = result.loop.sensor.modal_noise_nm(cal.reconstructor)
    period = request.frames(request.period)

    def new_ogtl():
        return ogtl_task(request.ogtl_settings, period, cal, cache, noise, request.chi_seeing)

    before, after = result.initial_gains, result.gains
    tt_after = before.copy()
    tt_after[TIP_TILT] = after[TIP_TILT]
    high_after = after.copy()
    high_after[TIP_TILT] = before[TIP_TILT]
    out: dict = {"ogtl": {"before": summary(result.before), "after": summary(result.after)}}
    for name, g in (("tt_after", tt_after), ("high_after", high_after)):
        out["ogtl"][name] = summary(evaluate(request, cal, design, g, 1.0, False, None, new_ogtl()))
    for k in (result.before.sensitivity, result.after.sensitivity):
        key = f"fixed_k_{k:.2f}"
        out[key] = {n: summary(evaluate(request, cal, design, g, k, True)) for n, g in (("before", before), ("after", after))}
    for kind in out.values():
        for name in [n for n in kind if n != "before"]:
            kind[name]["minus_before"] = paired(kind[name], kind["before"])
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--night", default="R9.4", choices=list(NIGHTS))
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--out", type=Path, default=RESULTS / "r94_split.json")
    a = p.parse_args()
    cache = ArrayCache(default_cache_dir())
    code = code_fingerprint()  # the code this run imports, not what the files hold when it ends
    request = night_request(a.night, a.seed)
    t0 = time.perf_counter()
    result = optimize(request, cache)
    if result.diverged_at is not None:
        print(f"diverged at frame {result.diverged_at} ({result.diverged_in})")
        return
    row = {
        "night": a.night,
        "seed": a.seed,
        "seeing": request.run.seeing_arcsec,
        "k_run": [float(k) for k in result.sensitivities],
        "safety_restores": result.safety_events,
        "gains": {"before": result.initial_gains.tolist(), "after": result.gains.tolist()},
        "evaluations": split(request, cache, result),
        **provenance(code),
    }
    row["seconds"] = time.perf_counter() - t0
    a.out.write_text(json.dumps(row, default=float, indent=1) + "\n")
    for kind, rows in row["evaluations"].items():
        for name, m in rows.items():
            d = m.get("minus_before")
            print(
                f"{kind:14s} {name:11s} {m['strehl']:.3f}  k_end {m['k_end']:.2f}  {m['residual_nm']:.0f} nm"
                + (f"  {d[0]:+.3f} ± {d[1]:.3f}" if d else "")
            )


if __name__ == "__main__":
    main()
