"""The loop's own optical gains against the table MGM's plant is built from.  With OGTL, MGM's
plant for mode i is chi_i = gamma_i / gamma_30 of the optical-gain table (``chi_model``): a
model residual (von Karman at the seeing, the controlled modes' amplitude cut to 10 %).  Here
gamma_i is measured around the residuals of the loop itself: one grid point of
`optimize_magnitudes.py` (same request), the *before* evaluation's loop (initial gains, OGTL
settled from k = 1), then every ``--gap`` seconds its residual OPD, around which each mode's
push-pull response is projected on its calibrated column, as ``optics.optical_gains`` does
around the model's residuals.  A ratio gamma_i / gamma_30 of the loop above the table's means
MGM sees less loop gain on mode i than there is.  Not in CI (~1-2 min per point on one core).

Run:  python -m validation.loop_optical_gains --mag 16.5 --seeing 0.6 --seed 2 [--snapshots 12] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from soulctl.files import atomic_write_text
from soulctl.loop.chi_model import optical_gain_table
from soulctl.loop.evaluation import settled_evaluation_loop
from soulctl.optics.calibration import calibration_sensor, mode_maps, push_pull
from validation.optimize_magnitudes import point_loops
from validation.provenance import provenance

MODES = (1, 2, 3, 10, 30, 60, 100)  # Tip, Tilt, focus, a few orders up; 30 is OGTL's probe


def loop_gains(loop, cal, modes: list[int], snapshots: int, gap_frames: int) -> np.ndarray:
    """(snapshots, len(modes)) gamma_i around ``loop``'s residual, one snapshot every ``gap_frames``."""
    sensor = calibration_sensor(cal.setup.pyramid)
    pupil = sensor.pupil
    idx = [m - 1 for m in modes]
    maps = mode_maps(cal.basis.shapes(pupil), pupil)[idx]
    D0 = cal.interaction_matrix[:, idx]
    norm = np.sum(D0**2, axis=0)
    out = []
    for _ in range(snapshots):
        loop.run(gap_frames - 1)
        opd = np.zeros((pupil.n_pixels,) * 2, dtype=np.float32)
        opd[pupil.mask] = loop.step()
        out.append(np.sum(push_pull(sensor, maps, cal.setup.push_nm, around=opd) * D0, axis=0) / norm)
    return np.array(out)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mag", type=float, required=True)
    p.add_argument("--seeing", type=float, required=True)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--snapshots", type=int, default=12)
    p.add_argument("--gap", type=float, default=0.05, help="seconds between snapshots")
    p.add_argument("--out", type=Path)
    a = p.parse_args()
    point = point_loops(a.mag, a.seeing, a.seed)
    request, cal, cache, obs = point.request, point.cal, point.cache, point.request.run.observation
    initial = point.session.loop.rtc_parameters.gains
    loop = settled_evaluation_loop(request, cal, point.design, initial, 1.0, False, None, point.session.new_ogtl())
    modes = [m for m in MODES if m <= cal.basis.n_modes]
    g = loop_gains(loop, cal, modes, a.snapshots, max(1, round(a.gap * obs.frame_rate_hz)))
    table = optical_gain_table(cal, cache, request.chi_seeing)[[m - 1 for m in modes]]
    probe = modes.index(request.ogtl_settings.mode)
    mean = g.mean(axis=0)
    out = {
        "point": {"mag": a.mag, "seeing": a.seeing, "seed": a.seed},
        **provenance(),
        "k_settled": loop.rtc_parameters.sensitivity,
        "k_gamma_probe": loop.rtc_parameters.sensitivity * float(mean[probe]),
        "modes": modes,
        "gamma_loop": mean.round(4).tolist(),
        "gamma_loop_error": (g.std(axis=0, ddof=1) / np.sqrt(len(g))).round(4).tolist(),
        "gamma_table": table.round(4).tolist(),
        "chi_loop": (mean / mean[probe]).round(3).tolist(),
        "chi_table": (table / table[probe]).round(3).tolist(),
    }
    text = json.dumps(out, indent=1)
    print(text)
    if a.out:
        atomic_write_text(a.out, text)


if __name__ == "__main__":
    main()
