"""Where does MGM with OGTL lose at R14.5?  Two checks on one grid point of
`optimize_magnitudes.py` (its request, with the default mirror unless --influence says otherwise):

1. *The Welch kernel* (``welch_bias``): MGM's Tip/Tilt optimum from a model POL PSD built from
   the inputs of the run's ``loop.optimize.noise_aware_gains`` call (frozen-flow Tip/Tilt, the
   vibration lines of each axis - that function puts their mean on both - and the WFS noise),
   exact on a fine grid, against the optimum from
   Welch estimates of a synthetic Gaussian POL with that PSD, for segments of 256-8192 frames:
   does the Hann kernel's spread of the 0.5-Hz-wide 13 Hz line over a 512-frame segment's
   bins move the optimum?
2. *Which gains lose* (``scan``): the optimisation, then the paired evaluation (``evaluate``,
   OGTL from k = 1 as `optimize gains` evaluates) of the initial gains with Tip/Tilt scaled by
   ``--scales``, and of the two cross combinations: the initial gains with MGM's Tip/Tilt, and
   MGM's gains with the initial Tip/Tilt.

The model's inputs are taken from the run itself (``noise_aware_gains`` wrapped for the call
the optimisation makes), so that check 1 uses exactly what the run used.  Not in CI (~12 min
at R14.5 on one core).

Run:  python -m validation.mgm_tip_tilt --mag 14.5 --seeing 0.6 --seed 2 [--out FILE]
"""

from __future__ import annotations

import json

import numpy as np

import soulctl.loop.gain_policy as gain_policy
from soulctl.cli.common import default_cache_dir
from soulctl.control import mgm
from soulctl.control.gains import unit_loops
from soulctl.disturbance.turbulence import TurbulenceTipTilt
from soulctl.files import atomic_write_text
from soulctl.loop.evaluation import evaluate
from soulctl.loop.optimisers import request_ogtl_task
from soulctl.loop.optimize import optimize
from soulctl.loop.run import calibration_for
from soulctl.loop.schedule import OptimizeRequest
from soulctl.optics.cache import ArrayCache
from validation.optimize_magnitudes import WINDOWS, point_arguments, point_request
from validation.provenance import code_fingerprint, provenance

SEGMENTS = (256, 512, 1024, 2048, 4096, 8192)
SYNTHETIC_FRAMES = 2**20  # ~23 min at 750 Hz: the long-series estimate is the Welch estimator's mean
PSD_CHUNK = 4096  # frequencies of the Tip/Tilt model PSD computed at a time (~100 MB)
WINDOW_FRAMES = 6400  # the short windows' length: at least 5 segments of 1280 frames


def model_psd(args: tuple, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(f, Tip/Tilt model POL PSD (2, F), nm^2/Hz) on the rfft grid of ``frames``, from the
    arguments of the run's ``noise_aware_gains`` call (as it builds it)."""
    obs, _, _, _, _, atm, noise_nm, vibrations, nm_per_mas = args[:9]
    rate = obs.frame_rate_hz
    f = np.fft.rfftfreq(frames, 1.0 / rate)
    psd = np.empty((2, f.size))
    model = TurbulenceTipTilt(atm.seeing_arcsec, atm.L0_m, atm.effective_wind_speed_m_s)
    parts = np.array_split(f[1:], max(1, f.size // PSD_CHUNK))  # the PSD's integral holds a grid per frequency
    tt = np.concatenate([model.psd(part) for part in parts])
    for mode, axis in enumerate(("tip", "tilt")):
        lines = vibrations.psd(f[1:], axis) if vibrations is not None else 0.0
        psd[mode, 1:] = (tt + lines) * nm_per_mas**2 + np.asarray(noise_nm)[mode] ** 2 / (rate / 2)
    psd[:, 0] = psd[:, 1]
    return f, psd


def welch_bias(args: tuple, seed: int = 0) -> dict:
    """Check 1: the exact optimum against Welch estimates of a synthetic POL of the model PSD."""
    obs, structure, forgetting, chi = args[:4]
    rate, delay = obs.frame_rate_hz, obs.delay_frames
    unit, ba = unit_loops(obs, structure, forgetting, 2)
    chi2 = np.asarray(chi[:2], dtype=float)
    f, psd = model_psd(args, SYNTHETIC_FRAMES)
    upper = mgm.gain_limits(unit, chi2, delay, rate, mgm.MgmSettings().margin, ba)
    exact = mgm.optimal_gains(psd[:, 1:], mgm.unit_open_loops(unit, chi2, delay, rate, f[1:], ba), upper)
    rng = np.random.default_rng(seed)
    spectrum = np.sqrt(psd * rate * SYNTHETIC_FRAMES / 2) * np.exp(2j * np.pi * rng.random(psd.shape))
    spectrum[:, 0] = 0.0
    pol = np.fft.irfft(spectrum, n=SYNTHETIC_FRAMES, axis=1).T
    out = {"exact": exact.tolist(), "segments": {}}
    for segment in SEGMENTS:
        machine = mgm.ModalGainMachine(tuple(unit), chi2, delay, rate, mgm.MgmSettings(segment=segment), ba)
        n = max(WINDOW_FRAMES, 5 * segment)
        short = np.array([_welch_optimum(machine, pol[lo : lo + n]) for lo in range(0, SYNTHETIC_FRAMES - n, SYNTHETIC_FRAMES // 8)])
        long = _welch_optimum(machine, pol)
        mean, sd = short.mean(0), short.std(0)
        out["segments"][segment] = {"long_series": long.tolist(), "windows_mean": mean.tolist(), "windows_sd": sd.tolist()}
        print(f"segment {segment:5d}: long {np.round(long, 4)}, {len(short)} windows of {n} frames {np.round(mean, 4)} ± {np.round(sd, 4)}")
    print(f"exact (model PSD on {SYNTHETIC_FRAMES} frames): {np.round(exact, 4)}", flush=True)
    return out


def _welch_optimum(machine: mgm.ModalGainMachine, pol: np.ndarray) -> np.ndarray:
    """MGM's optimum (without its noise rule) from the Welch PSD of the POL ``pol``."""
    m = machine
    return mgm.optimal_gains(m.pol_psd(pol), m.open_loops, m.upper, m.settings.grid, m.whitening)


def scan(request: OptimizeRequest, result, cache: ArrayCache, scales: list[float]) -> list[dict]:
    """Check 2: paired evaluations of the initial gains with Tip/Tilt scaled, and the cross
    combinations of the initial and MGM's gains (as ``evaluate_pair`` evaluates)."""
    cal = calibration_for(request.run, cache)
    design = request.run.design_gains()
    k, offsets = result.sensitivities[0], result.offsets[0]
    noise = result.loop.sensor.modal_noise_nm(cal.reconstructor)

    initial, final = np.array(result.initial_gains), np.array(result.gains)
    sets = {f"initial, Tip/Tilt x {s:g}": np.concatenate([initial[:2] * s, initial[2:]]) for s in scales}
    sets["initial, MGM's Tip/Tilt"] = np.concatenate([final[:2], initial[2:]])
    sets["MGM's, initial Tip/Tilt"] = np.concatenate([initial[:2], final[2:]])
    sets["MGM's"] = final
    rows = []
    for name, gains in sets.items():
        m = evaluate(request, cal, design, gains, k, offsets, None, request_ogtl_task(request, cal, cache, noise))
        row = {"gains": name, "tip_tilt": gains[:2].tolist(), "strehl": m.strehl, "windows": list(m.window_strehls)}
        rows.append({**row, "tt_jitter_mas": m.tt_jitter_mas, "k": m.sensitivity})
        tt = np.round(gains[:2], 3)
        print(f"{name:28s} Tip/Tilt {tt}: Strehl {m.strehl:.4f}, jitter {m.tt_jitter_mas:.2f} mas, k {m.sensitivity:.3f}", flush=True)
    return rows


def main() -> None:
    p = point_arguments(__doc__, 14.5, 0.6, 2)
    p.add_argument("--influence", choices=("gaussian", "thin-plate"), default="thin-plate")
    p.add_argument("--scales", default="0.7,0.85,1,1.2", help="Tip/Tilt scales of the initial gains")
    p.add_argument("--windows", type=int, default=WINDOWS)
    a = p.parse_args()
    launched = code_fingerprint()  # the code imported now, whatever is installed while it runs
    request = point_request(a.mag, a.seeing, a.seed, a.variant, a.windows, influence=a.influence, wfs_field=a.wfs_field)
    windows = request.windows
    cache = ArrayCache(default_cache_dir())
    calls = []
    model = gain_policy.noise_aware_gains

    def recorded(*args, **kwargs):  # the run's own model inputs, for check 1
        calls.append(args)
        return model(*args, **kwargs)

    gain_policy.noise_aware_gains = recorded
    try:
        result = optimize(request, cache)
    finally:
        gain_policy.noise_aware_gains = model
    if result.diverged_at is not None:
        raise SystemExit(f"the optimisation diverged at frame {result.diverged_at}")
    print(f"MGM: Tip/Tilt {np.round(result.initial_gains[:2], 3)} -> {np.round(result.gains[:2], 3)}", flush=True)
    out = {"mag": a.mag, "seeing": a.seeing, "seed": a.seed, "variant": a.variant, "influence": a.influence, "windows": windows}
    out["welch"] = welch_bias(calls[0])
    out["scan"] = scan(request, result, cache, [float(s) for s in a.scales.split(",")])
    out |= provenance(launched)
    if a.out is not None:
        atomic_write_text(a.out, json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
