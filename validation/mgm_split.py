"""Which of MGM's gains lose at a grid point?  From a `mgm_nu.py` result (the run's initial and
MGM's gains, *before*'s settled k; the same request, so the same turbulence and noise), the
paired evaluation (``evaluate``: OGTL from k = 1, then the windows at *before*'s k, as
`optimize gains` judges) of the initial gains with one group (``gain_groups``) replaced by
MGM's, or MGM's gains with one group replaced by the initial.  ``initial`` is the pairing's
reference: its own OGTL must settle to the k recorded, and each set's difference is taken
window by window against it (the standard error of the paired differences).

The sets are independent: run them as separate processes (``--sets``) and pair the files
with ``--pair``.  Not in CI (~10 min per set at R14.5 on 24 windows on one core).

Run:  python -m validation.mgm_split RESULT.json --sets initial,"initial with MGM's tip-tilt" --out FILE
      python -m validation.mgm_split --pair FILE...
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from soulctl.cli.common import default_cache_dir
from soulctl.control.gains import gain_groups
from soulctl.files import atomic_write_text
from soulctl.loop.evaluation import FrozenK, evaluate
from soulctl.loop.optimisers import request_ogtl_task
from soulctl.loop.optimize import OptimizeResult
from soulctl.loop.run import calibration_for, closed_loop_for
from soulctl.loop.schedule import session_seconds
from soulctl.optics.cache import ArrayCache
from validation.optimize_magnitudes import point_request
from validation.provenance import code_fingerprint, provenance


def swapped(gains: np.ndarray, other: np.ndarray, group: slice) -> np.ndarray:
    """``gains`` with ``group`` taken from ``other``."""
    out = gains.copy()
    out[group] = other[group]
    return out


def gain_sets(initial: np.ndarray, final: np.ndarray) -> dict[str, np.ndarray]:
    """The initial gains, and each group of one gain set swapped for the other's."""
    sets = {"initial": initial}
    for group, idx in gain_groups(len(initial)):
        sets[f"initial with MGM's {group}"] = swapped(initial, final, idx)
        sets[f"MGM's with the initial {group}"] = swapped(final, initial, idx)
    sets["MGM's"] = final
    return sets


def evaluate_sets(recorded: dict, names: list[str]) -> list[dict]:
    """Each named set's windows, at the recorded k (``initial``: at its own settled k)."""
    request = point_request(recorded["mag"], recorded["seeing"], recorded["seed"], recorded["variant"], recorded["windows"])
    if request.run.ncpa is not None and request.run.ncpa.compensated:
        raise SystemExit("mgm_split freezes k without NCPA offsets; this point's request applies them")
    cache = ArrayCache(default_cache_dir())
    cal = calibration_for(request.run, cache)
    structure = request.run.sampled_structure()
    design = request.run.design_gains()
    sensor = closed_loop_for(request.run, cal, design, structure, duration_s=session_seconds(request)).sensor
    noise = sensor.modal_noise_nm(cal.reconstructor)
    sets = gain_sets(np.array(recorded["initial_gains"]), np.array(recorded["final_gains"]))
    k = recorded["settled_k"]
    rows = []
    for name in names:
        freeze = None if name == "initial" else FrozenK(k, False)
        task = request_ogtl_task(request, cal, cache, noise)
        m = evaluate(request, cal, design, sets[name], k, False, None, task, freeze)
        groups = {g: float(sets[name][idx].mean()) for g, idx in gain_groups(len(sets[name]))}
        own = m.settled.k if m.settled else None
        if name == "initial" and own != k:
            raise SystemExit(f"the initial gains settled at k = {own}, not the recorded {k}: not the recorded run")
        rows.append({"gains": name, "groups": groups, "strehl": m.strehl, "windows": list(m.window_strehls), "own_settled_k": own})
        print(f"{name:36s} Strehl {m.strehl:.4f}, own settled k {own:.4f} (recorded {k:.4f})", flush=True)
    return rows


def paired_differences(rows: list[dict]) -> list[tuple[float, float | None]]:
    """Each set's mean difference to ``initial`` window by window, and its standard error, as
    the grid judges a row (``OptimizeResult.strehl_difference``)."""
    reference = SimpleNamespace(window_strehls=next(r["windows"] for r in rows if r["gains"] == "initial"))
    return [
        OptimizeResult.strehl_difference(SimpleNamespace(before=reference, after=SimpleNamespace(window_strehls=r["windows"])))
        for r in rows
    ]


def pair(rows: list[dict]) -> None:
    """The table of the sets' paired differences to ``initial``."""
    for r, (diff, error) in zip(rows, paired_differences(rows)):
        groups = ", ".join(f"{v:.3f}" for v in r["groups"].values())
        print(f"| {r['gains']} | {groups} | {diff:+.4f} ± {error or 0.0:.4f} | {r['own_settled_k']:.2f} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("result", nargs="?", type=Path, help="a mgm_nu.py result")
    p.add_argument("--sets", default="initial", help="comma-separated names of gain_sets' sets")
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--pair", nargs="+", type=Path, help="run nothing: pair these files' sets")
    a = p.parse_args()
    if a.pair:
        pair([r for f in a.pair for r in json.loads(f.read_text())["sets"]])
        return
    launched = code_fingerprint()
    recorded = json.loads(a.result.read_text())
    out = {k: recorded[k] for k in ("mag", "seeing", "seed", "variant", "windows", "settled_k")}
    out["sets"] = evaluate_sets(recorded, a.sets.split(","))
    out |= provenance(launched)
    if a.out is not None:
        atomic_write_text(a.out, json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
