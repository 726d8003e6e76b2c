"""A runaway in a paired evaluation, followed by its Tip: the same loop closed afresh on one grid point's
turbulence and noise (``settled_evaluation_loop``'s sequence: k = 1 for the closing, then OGTL
from k = 1 for the settling), at several gain sets, its Tip/Tilt residual followed every
0.2 s.  Found at R11.9 1.5" seed 3 (mgm+ogtl): an excursion at t ~ 12 s carries every gain
set toward or past the pyramid's range; the initial gains come back from a Tip of 0.64 um,
MGM's run away to divergence (docs/physics.md, "Over the magnitudes").  The Tip followed here
is the projection of what runs away, a shape of the pupil's rim in a false lock, not a lost
Tip: ``edge_runaway.py`` shows the pyramid's own Tip/Tilt signal at zero throughout.

The gain sets: ``initial`` and ``mgm`` (MGM's result, from ``--gains`` written by a previous
run or from a fresh `optimize gains` of the point, ~10 min), and their two mixtures
(``mgm_tt``: MGM's Tip/Tilt with the initial higher modes; ``mgm_high``: the converse).
Not in CI (~3 min per gain set on one core at R11.9).

Run:  python -m validation.lock_loss --mag 11.9 --seeing 1.5 --seed 3 \
          [--gains validation/results/lock_loss_r11.9_1.5_s3_gains.npz] [--modulation L] [--evaluate] [--out FILE]

``--modulation``: the pyramid modulated at L lambda/D instead of the table's, the same gain
sets (a new calibration and optical-gain table, ~5 min, cached).  ``--evaluate``: also each
set that held, measured as the paired evaluation measures it (``evaluate``, ~8 min a set).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from soulctl.files import atomic_write_text
from soulctl.loop.evaluation import _new_loop, evaluate
from soulctl.loop.optimize import optimize
from soulctl.loop.run import closing_frames
from soulctl.loop.schedule import evaluation_settle_s
from soulctl.loop.simulation import LoopDiverged
from validation.optimize_magnitudes import point_loops
from validation.provenance import provenance

STEP_S = 0.2  # the path's sampling


def gain_sets(initial: np.ndarray, mgm: np.ndarray) -> dict[str, np.ndarray]:
    """The initial and MGM's gains and their two Tip/Tilt - higher-mode mixtures."""
    return {"initial": initial, "mgm": mgm, "mgm_tt": np.r_[mgm[:2], initial[2:]], "mgm_high": np.r_[initial[:2], mgm[2:]]}


def settle_path(point, gains: np.ndarray) -> dict:
    """The evaluation loop's settling at ``gains``: per STEP_S, k, the residual RMS and the
    Tip/Tilt residual's mean and RMS (nm); where it diverged, if it did.  The sequence of
    ``settled_evaluation_loop``, repeated here because that function's loop is out of reach
    once it raises LoopDiverged, and the path up to the divergence is what is wanted."""
    request, rate = point.request, point.request.run.observation.frame_rate_hz
    loop = _new_loop(request, point.cal, point.design, request.run.sampled_structure())
    loop.set_gains(gains)
    loop.rtc_parameters.hold_slope_offset()
    loop.run(closing_frames(rate))
    loop.add_aux_loop(point.session.new_ogtl())
    end, step = loop.frame + request.frames(evaluation_settle_s(request.period, True)), request.frames(STEP_S)
    path: list[dict] = []
    diverged = None
    try:
        while loop.frame < end:
            start = loop.frame
            loop.run(step)
            rms = np.asarray(loop.telemetry.residual_rms_nm[start : loop.frame])
            tt = loop.telemetry.series("residual_tt")[start : loop.frame]
            path.append(
                {
                    "t_s": loop.frame / rate,
                    "k": loop.rtc_parameters.sensitivity,
                    "residual_nm": float(np.sqrt(np.mean(rms**2))),
                    "tt_mean_nm": tt.mean(axis=0).tolist(),
                    "tt_rms_nm": np.sqrt(np.mean(tt**2, axis=0)).tolist(),
                }
            )
    except LoopDiverged as e:
        diverged = {"frame": e.frame, "residual_nm": e.residual_nm}
    return {"path": path, "diverged": diverged}


def windows(point, gains: np.ndarray) -> dict:
    """The paired evaluation's measurement of ``gains`` (``evaluate``: OGTL from k = 1, its
    settling, then the windows at the loop's own k): Strehl ratio, per window, residual, k."""
    m = evaluate(point.request, point.cal, point.design, gains, 1.0, ogtl=point.session.new_ogtl())
    return {"strehl": m.strehl, "window_strehls": m.window_strehls, "residual_nm": m.residual_nm, "k": m.sensitivity}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mag", type=float, default=11.9)
    p.add_argument("--seeing", type=float, default=1.5)
    p.add_argument("--seed", type=int, default=3)
    p.add_argument("--gains", type=Path, default=None, help="npz with 'initial' and 'mgm' (written here when absent)")
    p.add_argument("--sets", default="initial,mgm,mgm_tt,mgm_high")
    p.add_argument("--modulation", type=float, default=None, help="lambda/D instead of the table's (the same gain sets)")
    p.add_argument("--evaluate", action="store_true", help="also each set's paired-evaluation windows (its Strehl ratio)")
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args()
    point = point_loops(a.mag, a.seeing, a.seed, modulation=a.modulation)
    if a.gains is not None and a.gains.exists():
        saved = np.load(a.gains)
        initial, mgm = saved["initial"], saved["mgm"]
    else:
        result = optimize(point.request, point.cache)
        initial, mgm = np.asarray(result.initial_gains), np.asarray(result.gains)
        if a.gains is not None:
            np.savez(a.gains, initial=initial, mgm=mgm)
    sets = gain_sets(initial, mgm)
    modulation = point.request.run.observation.modulation_lambda_over_d
    out = {"mag": a.mag, "seeing": a.seeing, "seed": a.seed, "modulation": modulation, **provenance(), "sets": {}}
    for name in a.sets.split(","):
        out["sets"][name] = res = settle_path(point, sets[name])
        worst = max(res["path"], key=lambda s: abs(s["tt_mean_nm"][0]))
        print(f"{name}: diverged {res['diverged']}; largest Tip mean {worst['tt_mean_nm'][0]:.0f} nm at {worst['t_s']:.1f} s", flush=True)
        if a.evaluate and res["diverged"] is None:
            res["evaluation"] = windows(point, sets[name])
            print(f"{name}: Strehl ratio {res['evaluation']['strehl']:.4f} over the windows", flush=True)
        if a.out:
            atomic_write_text(a.out, json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
