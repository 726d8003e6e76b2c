"""Why MGM's low-order gains at R13 sit below the gains that maximise the evaluation's Strehl
(issue: MGM and OGTL that never drive the loop unstable; `r13_low_order_scan.py` found the
Strehl ratio peaking with modes 3-10 ~1.5x above MGM's final gain).  Not in CI (~10 min on
one core).

The paper's R13 case (20x20, 980 Hz, FeII, 1.0", 5 m/s, seed 2, no NCPA) at fixed gains, k =
3.3 (OGTL's k there) and MGM's final loop gains g k per group:

1. *MGM's estimate per span.*  One 16 s loop on the screens of the optimisation (the same
   session length, so the same turbulence): for each span of frames, the true disturbance
   variance of modes 3-10 and MGM's optimum for them (offline, the machine of the run, the
   prewhitened POL of the span, chi scale 1), converted to g k.  The evaluation measures
   frames ~500-4500; the live MGM updated on frames 8232-15092.
2. *The truth in the evaluation's frames.*  The same loop with modes 3-10 at several g k,
   3 s from the evaluation's start: the true residual variance of modes 3-10 (whose minimum
   is the optimum MGM aims at) and the FeII Strehl ratio.

Run:  python -m validation.r13_mgm_windows [--seed 2] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from soulctl.control import mgm
from soulctl.files import atomic_write_text
from soulctl.loop.evaluation import settled_evaluation_loop
from soulctl.loop.metrics import band_wavelength, pseudo_open_loop
from soulctl.loop.optimisers import mgm_machine
from soulctl.loop.optimize import plant_model
from validation.provenance import provenance
from validation.r13_low_order_scan import r13_case  # noqa: E402

K = 3.3  # OGTL's k at the end of the optimisation (r13_low_order_scan.json: 3.25-3.29)
# MGM's final g k per group at this seed (modes 1-2, 3-10, 11-30, 31-60, 61-120, 121-250)
PRODUCTS = (
    (slice(0, 2), 0.6),
    (slice(2, 10), 0.559),
    (slice(10, 30), 0.455),
    (slice(30, 60), 0.403),
    (slice(60, 120), 0.299),
    (slice(120, None), 0.194),
)
LOW = slice(2, 10)
SPANS = ((500, 4500), (4500, 8500), (8500, 12500), (8232, 15092), (12000, 16000))
SCAN = (0.4, 0.56, 0.7, 0.84, 1.0, 1.2)
FIELDS = ("measured_modes", "command_modes", "disturbance_modes", "residual_modes")


def recorded_loop(request, cal, design, gains, seconds: float, psf_band: str | None = None):
    """The evaluation's loop at ``gains`` and k = K for ``seconds``: the fields recorded per
    frame, the first frame recorded and, with ``psf_band``, the Strehl ratio."""
    loop = settled_evaluation_loop(request, cal, design, gains, K)
    rows: dict[str, list] = {name: [] for name in FIELDS}
    append = loop.telemetry.append_frame

    def capture(**kw):
        for name in FIELDS:
            rows[name].append(np.asarray(kw[name], dtype=float).copy())
        append(**kw)

    loop.telemetry.append_frame = capture
    first = loop.frame
    psf = loop.psf_accumulator(band_wavelength(psf_band)) if psf_band else None
    loop.run(int(round(seconds * request.run.observation.frame_rate_hz)), psf=psf)
    return {name: np.array(v) for name, v in rows.items()}, first, (psf.strehl if psf else None), loop.delay.delay_frames


def spans_of_mgm(request, cal, cache, design, gains) -> list[dict]:
    """Part 1: MGM's offline optimum (g k) and the disturbance variance of modes 3-10 per span."""
    obs = request.run.observation
    rows, first, _, delay = recorded_loop(request, cal, design, gains, 16.0)
    chi = plant_model(cal, cache, True, 30)
    machine = mgm_machine(obs, request.run.sampled_structure(), chi, mgm.MgmSettings())
    mirror = pseudo_open_loop(np.zeros_like(rows["command_modes"]), rows["command_modes"], delay, machine.structure)
    pol = rows["measured_modes"] / chi + mirror
    skip = int(delay) + 1
    out = []
    for a, b in SPANS:
        i0, i1 = max(a - first, 0) + skip, min(b - first, len(pol))
        g, _ = machine.optimum(pol[i0:i1])
        variance = float(rows["disturbance_modes"][i0:i1, LOW].var(axis=0).sum())
        out.append({"frames": [a, b], "disturbance_variance_nm2": variance, "mgm_gk": float(g[LOW].mean() * K)})
        print(f"frames {a}-{b}: disturbance variance of modes 3-10 {variance:.3g} nm2, MGM's g k {out[-1]['mgm_gk']:.3f}", flush=True)
    return out


def scan_in_evaluation_frames(request, cal, design, gains) -> list[dict]:
    """Part 2: residual variance of modes 3-10 and FeII Strehl against their g k."""
    out = []
    for gk in SCAN:
        g = gains.copy()
        g[LOW] = gk / K
        rows, _, strehl, _ = recorded_loop(request, cal, design, g, 3.0, "FeII")
        variance = float(rows["residual_modes"][:, LOW].var(axis=0).sum())
        out.append({"gk": gk, "residual_variance_nm2": variance, "strehl": strehl})
        print(f"modes 3-10 at g k {gk:.2f}: residual variance {variance:.0f} nm2, FeII Strehl {strehl:.4f}", flush=True)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=2)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "r13_mgm_windows.json")
    a = p.parse_args()
    request, cache, cal, design = r13_case(a.seed)  # the optimisation's session, hence its screens
    gains = np.empty(cal.basis.n_modes)
    for modes, gk in PRODUCTS:
        gains[modes] = gk / K
    out = {"seed": a.seed, **provenance(), "k": K, "spans": spans_of_mgm(request, cal, cache, design, gains)}
    out["scan"] = scan_in_evaluation_frames(request, cal, design, gains)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(a.out, json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
