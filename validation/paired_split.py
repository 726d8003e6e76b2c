"""Which part of an optimisation's loss is the gains' and which is OGTL's k?  One grid point of
`optimize_magnitudes.py` (same request), then the paired evaluation of the four combinations of
{initial, optimised} gains x {k before, k after}, k frozen (the grid's rule before OGTL ran in
its evaluation; now both gain sets start from k before with OGTL running: ``evaluate_pair``).
Not in CI (~8 min for a 20x20 point on one core).

Run:  python -m validation.paired_split --mag 11.9 --seeing 1.5 --seed 1 [--variant mgm+ogtl] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from soulctl.cli.common import default_cache_dir
from soulctl.control.gains import gain_groups
from soulctl.files import atomic_write_text
from soulctl.loop.evaluation import evaluate
from soulctl.loop.optimize import optimize
from soulctl.loop.run import calibration_for
from soulctl.loop.schedule import OptimizeRequest, default_period_s
from soulctl.observation import observation_for_magnitude
from soulctl.optics.cache import ArrayCache
from validation.optimize_magnitudes import DURATION_PERIODS, MEASURE_S, WINDOW_S, WINDOWS, _run, windows_for
from validation.provenance import provenance


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mag", type=float, required=True)
    p.add_argument("--seeing", type=float, required=True)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--variant", default="mgm+ogtl")
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args()
    method, ogtl = a.variant.split("+")[0], a.variant.endswith("+ogtl")
    obs = observation_for_magnitude(a.mag)
    windows = windows_for(obs.frame_rate_hz, WINDOWS)
    duration = DURATION_PERIODS * default_period_s(obs)
    run = _run(obs, a.seeing, a.seed)
    request = OptimizeRequest(
        run=run, method=method, duration_s=duration, ogtl=ogtl, measure_s=MEASURE_S, windows=windows, window_s=WINDOW_S
    )
    cache = ArrayCache(default_cache_dir())
    r = optimize(request, cache)
    cal = calibration_for(request.run, cache)
    design = request.run.design_gains()
    (k0, k1), (o0, o1) = r.sensitivities, r.offsets
    cells = {}
    for gname, g in (("initial", r.initial_gains), ("optimised", r.gains)):
        for kname, k, off in (("k_before", k0, o0), ("k_after", k1, o1)):
            m = evaluate(request, cal, design, g, k, off)
            cells[f"{gname} gains, {kname}"] = m.strehl
            print(f"{gname} gains at {kname} = {k:.3f}: {m.strehl:.4f}", flush=True)
    groups = {name: [float(r.initial_gains[m].mean()), float(r.gains[m].mean())] for name, m in gain_groups(len(r.gains))}
    print("group mean gains, initial -> optimised:", {n: f"{g[0]:.3f} -> {g[1]:.3f}" for n, g in groups.items()}, flush=True)
    out = {"mag": a.mag, "seeing": a.seeing, "seed": a.seed, "variant": a.variant, "k": [k0, k1], "strehl": cells, "gain_groups": groups}
    out |= provenance()
    if a.out is not None:
        atomic_write_text(a.out, json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
