"""Is MGM's loss with OGTL at R14.5 the paper's nu?  One grid point of `optimize_magnitudes.py`
(its request: the look-up table's observation, the default mirror), optimised as the grid runs
it, then the paired evaluation (``evaluate``, OGTL from k = 1, the windows at the k *before*'s
OGTL settled to, as `optimize gains` judges) of:

* the initial gains scaled by ``--scales`` (all modes at once);
* MGM's gains, and MGM's gains divided by nu (Eq. gainUpdate: g_RTC(kappa) =
  (1 - rho) g_RTC(kappa - 1) + rho nu g_hat(kappa) settles at nu g_hat, every gain 10 % below
  the model's optimum with the paper's nu = 0.9);
* MGM's gains carried from the k the run ended at to the k the windows run at (x k_run /
  k_eval, as ``MgmTask.update`` carries its own gains when OGTL moves k): the same loop gain
  g k gamma MGM designed, if the optical gain is the same in both loops.

The hypothesis: if the initial gains already sit near the model's optimum, lowering every gain
by nu costs a little on each mode and the sum is what the point loses; MGM's gains / nu then
recover it.  Measured (docs/physics.md, "Over the magnitudes"): the initial gains x 0.9 lose
nothing, MGM's / nu recover most of MGM's loss - MGM's optimum is itself low there.  Each
difference to the initial gains is given with the standard error of its paired windows.
Not in CI (~25 min at R14.5 on one core).

Run:  python -m validation.mgm_nu --mag 14.5 --seeing 1.0 --seed 2 [--windows 24] [--out FILE]
"""

from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path

import numpy as np

from soulctl.cli.common import default_cache_dir
from soulctl.control.gains import gain_groups
from soulctl.files import atomic_write_text
from soulctl.loop.evaluation import evaluate
from soulctl.loop.optimisers import request_ogtl_task
from soulctl.loop.optimize import optimize
from soulctl.loop.run import calibration_for
from soulctl.loop.schedule import OptimizeRequest
from soulctl.optics.cache import ArrayCache
from validation.optimize_magnitudes import WINDOWS, point_request
from validation.provenance import code_fingerprint, provenance


def paired(result, metrics) -> tuple[float, float | None]:
    """``metrics`` - the initial gains' evaluation of ``result``: the windows' paired mean and
    its standard error (``OptimizeResult.strehl_difference``)."""
    pair = copy.copy(result)
    pair.after = metrics
    return pair.strehl_difference()


def gain_sets(initial: np.ndarray, final: np.ndarray, nu: float, scales: list[float], k_ratio: float) -> dict[str, np.ndarray]:
    """The gain sets to evaluate besides the initial ones; ``k_ratio``: the run's final k
    over the k the windows run at."""
    sets = {f"initial x {s:g}": initial * s for s in scales}
    sets["MGM's"] = final
    sets[f"MGM's / nu ({nu:g})"] = final / nu
    sets[f"MGM's x k_run/k_eval ({k_ratio:.3f})"] = final * k_ratio
    return sets


def evaluate_sets(request: OptimizeRequest, result, cache: ArrayCache, sets: dict[str, np.ndarray]) -> list[dict]:
    """Each set's paired evaluation against the initial gains, at *before*'s settled k."""
    cal = calibration_for(request.run, cache)
    design = request.run.design_gains()
    k, offsets = result.sensitivities[0], result.offsets[0]
    noise = result.loop.sensor.modal_noise_nm(cal.reconstructor)
    rows = []
    for name, gains in sets.items():
        task = request_ogtl_task(request, cal, cache, noise)
        m = evaluate(request, cal, design, gains, k, offsets, None, task, result.before.settled)
        diff, error = paired(result, m)
        groups = {g: float(gains[idx].mean()) for g, idx in gain_groups(len(gains))}
        rows.append({"gains": name, "strehl": m.strehl, "difference": diff, "standard_error": error, "groups": groups})
        rows[-1]["own_settled_k"] = m.settled.k if m.settled else None
        print(f"{name:24s} Strehl {m.strehl:.4f}  difference {diff:+.4f} +- {error or float('nan'):.4f}", flush=True)
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mag", type=float, default=14.5)
    p.add_argument("--seeing", type=float, default=1.0)
    p.add_argument("--seed", type=int, default=2)
    p.add_argument("--scales", default="0.8,0.9,1.1", help="scales of all the initial gains")
    p.add_argument("--windows", type=int, default=WINDOWS, help="the paired evaluation's windows (the grid's: %(default)s)")
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args()
    launched = code_fingerprint()  # the code imported now, whatever is installed while it runs
    request = point_request(a.mag, a.seeing, a.seed, "mgm+ogtl", a.windows)
    obs, windows = request.run.observation, request.windows
    cache = ArrayCache(default_cache_dir())
    result = optimize(request, cache)
    if result.diverged_at is not None:
        raise SystemExit(f"the optimisation diverged at frame {result.diverged_at}")
    initial, final = np.array(result.initial_gains), np.array(result.gains)
    nu = request.settings_for_rate(obs.frame_rate_hz).nu
    print(f"before {result.before.strehl:.4f} -> after {result.after.strehl:.4f} (k {result.before.settled.k:.3f})", flush=True)
    out = {"mag": a.mag, "seeing": a.seeing, "seed": a.seed, "variant": "mgm+ogtl", "windows": windows, "nu": nu}
    out["before"], out["after"] = result.before.strehl, result.after.strehl
    out["settled_k"] = result.before.settled.k
    out["initial_gains"], out["final_gains"] = initial.tolist(), final.tolist()
    out["k_run"] = result.sensitivities[1]
    k_ratio = result.sensitivities[1] / result.before.settled.k
    scales = [float(s) for s in a.scales.split(",")]
    out["sets"] = evaluate_sets(request, result, cache, gain_sets(initial, final, nu, scales, k_ratio))
    out |= provenance(launched)
    if a.out is not None:
        atomic_write_text(a.out, json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
