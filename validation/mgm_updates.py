"""What MGM predicts at each of its updates in one grid point of `optimize_magnitudes.py` (its
request): per mode, the gain in force and MGM's optimum g_hat, and Eq. cost's J at both, from
the same mean POL PSD the update used (``loop.auxloops.MgmTask``).  The predicted gain of the
update is (J(g_now) - J(g_hat)) / J(g_hat); two standard errors of it: the scatter of the
windows in MGM's memory (each window's own PSD gives its own ratio), and Welch's, which MGM's
significance test reads (``mgm.improvement``).  A change MGM predicts to gain less than its
standard error is one the data cannot tell from no change.

Not in CI (the point's own cost: ~21 min at R14.5 1.0" with 24 windows on one core).

Run:  python -m validation.mgm_updates --mag 14.5 --seeing 1.0 --seed 2 --windows 24 [--out FILE]
"""

from __future__ import annotations

import json

import numpy as np

from soulctl.cli.common import default_cache_dir
from soulctl.control import mgm
from soulctl.files import atomic_write_text
from soulctl.loop import auxloops
from soulctl.loop.optimize import optimize
from soulctl.optics.cache import ArrayCache
from validation.optimize_magnitudes import WINDOWS, point_arguments, point_request
from validation.provenance import code_fingerprint, provenance

GROUPS = {"Tip/Tilt": slice(0, 2), "modes 3-120": slice(2, 120), "modes 121-N": slice(120, None)}


def predicted(task: auxloops.MgmTask, gains_now: np.ndarray, k: float) -> dict:
    """The update's prediction from the task's memory, in the machine's gains (RTC gains x
    the chi scale at the window's k, as the update converts them)."""
    m = task.machine
    psds = task.window_psds()
    scale = task.chi_scale(k)
    now = gains_now * scale
    hat, info = m.optimum_of_psd(psds.mean(axis=0))
    per_window = np.array([mgm.cost(p, m.open_loops, now, m.whitening) / mgm.cost(p, m.open_loops, hat, m.whitening) - 1 for p in psds])
    j_hat = mgm.cost(psds.mean(axis=0), m.open_loops, hat, m.whitening)
    se = per_window.std(axis=0, ddof=1) / np.sqrt(len(psds)) if len(psds) > 1 else np.full(now.size, np.nan)
    variance = mgm.mean_psd_variance([s for _, _, s in task.windows], m.settings.segment)
    delta, welch_se = mgm.improvement(psds.mean(axis=0), m.open_loops, now, hat, variance, m.whitening)
    return {
        "windows": len(psds),
        "scale": scale,
        "gains_now": gains_now.tolist(),
        "g_hat": (hat / scale).tolist(),
        "predicted_gain": (delta / j_hat).tolist(),
        "predicted_gain_se": se.tolist(),  # the windows' scatter
        "predicted_gain_welch_se": (welch_se / j_hat).tolist(),  # Welch's, as the significance test reads it
        "noise_dominated": info["noise_dominated"].tolist(),
    }


def summary(row: dict) -> str:
    parts = []
    for name, s in GROUPS.items():
        now, hat = np.array(row["gains_now"])[s], np.array(row["g_hat"])[s]
        if now.size == 0:
            continue
        gain, se, welch = (np.array(row[key])[s] for key in ("predicted_gain", "predicted_gain_se", "predicted_gain_welch_se"))
        moves = np.mean(gain > mgm.SIGNIFICANCE * welch)
        parts.append(
            f"{name}: g_hat/g {np.median(hat / now):.3f}, J gain {100 * np.median(gain):.2f} % ± {100 * np.median(se):.2f} "
            f"(Welch ± {100 * np.median(welch):.2f}; {100 * moves:.0f} % significant)"
        )
    return "; ".join(parts)


def main() -> None:
    p = point_arguments(__doc__, 14.5, 1.0, 2)
    p.add_argument("--windows", type=int, default=WINDOWS)
    a = p.parse_args()
    launched = code_fingerprint()
    request = point_request(a.mag, a.seeing, a.seed, a.variant, a.windows, wfs_field=a.wfs_field)
    rows: list[dict] = []
    update = auxloops.MgmTask.update

    def recorded(task, window, rtc):
        out = update(task, window, rtc)
        if out:
            row = predicted(task, np.asarray(window.gains, dtype=float), window.sensitivity)
            rows.append({"frame": window.first_frame + window.frames, **row, "held": out.get("held")})
            print(f"update {len(rows)} (frame {rows[-1]['frame']}): {summary(rows[-1])}", flush=True)
        return out

    auxloops.MgmTask.update = recorded  # type: ignore[method-assign]
    try:
        result = optimize(request, ArrayCache(default_cache_dir()))
    finally:
        auxloops.MgmTask.update = update  # type: ignore[method-assign]
    strehl = [m.strehl if m is not None else None for m in (result.before, result.after)]
    print(f"Strehl {strehl[0]} -> {strehl[1]}")
    out = {"mag": a.mag, "seeing": a.seeing, "seed": a.seed, "variant": a.variant, "windows": request.windows, "updates": rows}
    out |= {"initial_gains": list(result.initial_gains), "gains": list(result.gains), **provenance(launched)}
    out |= {"strehl": strehl}
    if a.out is not None:
        atomic_write_text(a.out, json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
