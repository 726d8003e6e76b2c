"""Strehl loss against mis-registration of the adaptive secondary on the pyramid (fidelity
issue, item 4): the loop calibrated as registered, run with the mirror shifted, rotated or
magnified (``optics.registration``), at the paper's bright operating point (R9.7: 1700 Hz,
40x40, 500 modes, H band) and at R13 (980 Hz, 20x20, 250 modes, FeII), 1.0" seeing, default
gains, the same seed and turbulence at every point.  The loop's loss of control at large
mis-registration is a result, not an error: the reconstructor then drives modes the mirror
no longer makes.  Each row also has the verdict of the eigenmodes of R D' (``control.coupling``:
how many are unstable, the gain margin), to set beside the Strehl ratio the loop reached.

    python -m validation.misregistration_curve [--duration 1] [--seeds 1] [--cases 0,1] [--out FILE]

Writes the rows as JSON and a figure (Strehl against shift, rotation and magnification) beside
them.  ~40 s per point on one core at R9.7.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

from soulctl.cli.common import default_cache_dir
from soulctl.files import atomic_write_text
from soulctl.loop.run import run
from soulctl.optics.cache import ArrayCache
from soulctl.optics.registration import Misregistration
from soulctl.run_config import RunConfig
from validation.provenance import provenance

OUT = Path(__file__).parent / "results" / "misregistration_curve.json"
CASES = [("R9.7", {"star.magnitude_r": 9.7, "run.band": "H"}), ("R13", {"star.magnitude_r": 13.0, "run.band": "FeII"})]
SHIFTS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.75, 1.0)  # actuator pitches, along x
ROTATIONS = (0.5, 1.0, 2.0, 3.0, 5.0)  # deg
MAGNIFICATIONS = (1.01, 1.02, 1.03, 1.05)


def points() -> list[tuple[str, float, Misregistration]]:
    out = [("shift", s, Misregistration(shift_x_pitch=s)) for s in SHIFTS]
    out += [("rotation", r, Misregistration(rotation_deg=r)) for r in ROTATIONS]
    return out + [("magnification", m, Misregistration(magnification=m)) for m in MAGNIFICATIONS]


def one(base: RunConfig, registration: Misregistration, cache) -> dict:
    t0 = time.perf_counter()
    r = run(dataclasses.replace(base, misregistration=registration).request(), cache)
    m = r.metrics
    row = {"diverged_at": r.diverged_at, "seconds": round(time.perf_counter() - t0, 1)}
    if m is not None:
        row |= {"strehl": m.strehl, "residual_nm": m.residual_nm, "tt_jitter_mas": m.tt_jitter_mas}
    if r.coupling is not None:  # the eigenmodes of R D' (control.coupling); chi = gamma_i at the seeing, k = 1
        c = r.coupling
        row |= {"unstable_eigenmodes": c.unstable, "gain_margin": c.margin, "largest_pole": c.largest_pole, "lost": r.failure() is not None}
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--duration", type=float, default=1.0)
    p.add_argument("--seeds", type=int, default=1)
    p.add_argument("--cases", default="0,1")
    p.add_argument("--out", type=Path, default=OUT)
    a = p.parse_args()
    cache = ArrayCache(default_cache_dir())
    done = [json.loads(x) for x in a.out.read_text().splitlines()] if a.out.exists() else []
    have = {(d["case"], d["kind"], d["value"], d["seed"]) for d in done}
    for i in (int(c) for c in a.cases.split(",")):
        label, values = CASES[i]
        for seed in range(1, a.seeds + 1):
            base = RunConfig().with_values(
                {**values, "ncpa.rms_nm": 0.0, "atmosphere.seeing_arcsec": 1.0, "run.duration_s": a.duration, "run.seed": seed}
            )
            for kind, value, registration in points():
                if (label, kind, value, seed) in have:
                    continue
                row = {"case": label, "kind": kind, "value": value, "seed": seed, **one(base, registration, cache), **provenance()}
                print(json.dumps(row), flush=True)
                done.append(row)
                atomic_write_text(a.out, "".join(json.dumps(d) + "\n" for d in done))
    figure(done, a.out.with_suffix(".png"))


def figure(rows: list[dict], path: Path) -> None:
    """Strehl against each kind of mis-registration, the registered point starting each curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6), sharey=True)
    units = {"shift": ("shift (actuator pitches)", 0.0), "rotation": ("rotation (deg)", 0.0), "magnification": ("magnification", 1.0)}
    for ax, (kind, (unit, origin)) in zip(axes, units.items()):
        for label, _ in CASES:
            mine = [d for d in rows if d["case"] == label and d["seed"] == 1]
            ref = [(origin, d.get("strehl") or 0.0) for d in mine if d["kind"] == "shift" and d["value"] == 0.0]
            pts = ref + sorted((d["value"], d.get("strehl") or 0.0) for d in mine if d["kind"] == kind and d["value"] != origin)
            if len(pts) > 1:
                line = ax.plot(*zip(*pts), "o-", label=label)[0]
                lost = [(d["value"], d.get("strehl") or 0.0) for d in mine if d["kind"] == kind and d.get("lost")]
                if lost:  # the eigenmodes of R D' call the loop lost (control.coupling)
                    ax.plot(*zip(*lost), "x", color=line.get_color(), markersize=11, mew=2)
        ax.set_xlabel(unit)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("Strehl ratio (x: lost, unstable eigenmodes)")
    axes[0].legend()
    fig.suptitle('Mis-registration of the adaptive secondary on the pyramid (1.0", default gains, seed 1)')
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
