"""A simulated twin of an observed night: `telemetry identify` on a "night" whose vibration
spectrum the identification has never seen, then `loop run --plant` with the identified
plant (another seed: the twin shares the statistics, not the realisation), and the two
records' pseudo-open-loop and residual Tip/Tilt compared (spectra plotted, jitter tabulated).

The night: the paper's R13 operating point (980 Hz, 20x20, 250 modes) at seeing 1.2" and
L0 30 m, with vibration lines unlike tables/lbt_vibrations.toml (11.2, 17.5 and 44 Hz).
Writes validation/results/twin_night.json and twin_night.png.

    python -m validation.twin_night [--duration 30]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from soulctl.files import atomic_write_text
from soulctl.identify.plant import read_plant
from soulctl.plots.figure import new_figure, save_figure
from validation.provenance import provenance

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "validation" / "results"
NIGHT_VIBRATIONS = """source = "twin validation: a night unlike tables/lbt_vibrations.toml"
[[line]]
frequency_hz = 11.2
damping = 0.015
tip_mas = 15.0
tilt_mas = 10.0
[[line]]
frequency_hz = 17.5
damping = 0.025
tip_mas = 6.0
tilt_mas = 8.0
[[line]]
frequency_hz = 44.0
damping = 0.02
tip_mas = 3.0
tilt_mas = 2.0
"""


def soulctl(*args, cwd: Path) -> str:
    return subprocess.run(["soulctl", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout


def psd(path: Path, cwd: Path) -> dict:
    return json.loads(soulctl("telemetry", "psd", str(path), "--modes", "1,2", "--pseudo-open-loop", "--json", cwd=cwd))


def realised_lines(seed: int, rate: float, first: int, frames: int) -> list:
    """Each night line's realised RMS (tip, tilt) over the identification's window (the loop's
    vibration draws regenerated from the seed)."""
    import tomllib

    from soulctl.disturbance.vibrations import VibrationSource, VibrationSpectrum
    from soulctl.loop.stages import VIBRATION_BLOCK

    spectrum = VibrationSpectrum.from_dict(tomllib.loads(NIGHT_VIBRATIONS), "night")
    _, vib_seed, _ = np.random.default_rng(seed).integers(0, 2**63, size=3)
    source = VibrationSource(spectrum, rate, np.random.default_rng(vib_seed))
    x = np.concatenate([source.next_lines(VIBRATION_BLOCK) for _ in range((first + frames) // VIBRATION_BLOCK + 1)], axis=1)
    rms = np.sqrt(np.mean(x[:, first : first + frames] ** 2, axis=1))
    return [(line.frequency_hz, float(r[0]), float(r[1])) for line, r in zip(spectrum.lines, rms)]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=30.0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        work = Path(d)
        (work / "night_vib.toml").write_text(NIGHT_VIBRATIONS)
        base = ["--config", str(ROOT / "examples" / "paper_r13_980hz.toml"), "--duration", str(args.duration)]
        night = soulctl("loop", "run", *base, "--seeing", "1.2", "--L0", "30", "--vibrations", "night_vib.toml", "--seed", "11",
                        "--telemetry", "night.h5", "--json", cwd=work)  # fmt: skip
        ident = json.loads(soulctl("telemetry", "identify", "night.h5", "--out", "plant.toml", "--json", cwd=work))
        twin = soulctl("loop", "run", *base, "--plant", "plant.toml", "--seed", "12", "--telemetry", "twin.h5", "--json", cwd=work)
        spectra = {"night": psd(work / "night.h5", work), "twin": psd(work / "twin.h5", work)}
        runs = {"night": json.loads(night), "twin": json.loads(twin)}
        plant = read_plant(work / "plant.toml")
    report = {
        "duration_s": args.duration,
        "identified": {
            "delay_frames": ident["delay_frames"]["value"],
            "delay_recorded": ident["delay_frames"]["recorded"],
            "seeing": ident["turbulence"]["seeing_arcsec"],
            "L0": ident["turbulence"]["L0_m"],
            "lines": [(x.frequency_hz, x.tip_mas, x.tilt_mas) for x in (plant.vibrations.lines if plant.vibrations else ())],
            "lines_realised": realised_lines(11, 980.0, ident["lines_window"]["first_frame"], ident["lines_window"]["frames"]),
        },
        "jitter_mas": {
            name: {
                "pseudo_open_loop_all": s["tt_jitter_mas"]["pseudo_open_loop"],
                "pseudo_open_loop_above_3hz": s["tt_jitter_above_3hz_mas"]["pseudo_open_loop"],
                "residual_all": s["tt_jitter_mas"]["measured_modes"],
            }
            for name, s in spectra.items()
        },
        "loop_metrics": {
            name: {k: r["metrics"].get(k) for k in ("strehl", "band", "tt_jitter_mas", "tt_jitter_pol_mas", "tt_jitter_pol_3hz_mas")}
            for name, r in runs.items()
        },
    }
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "twin_night.json", json.dumps(report | provenance(), indent=1))
    fig = new_figure((6.4, 4.8))
    ax = fig.subplots()
    for i, (name, s) in enumerate(spectra.items()):
        f = np.asarray(s["f_hz"])[1:]
        pol = np.asarray(s["psd_nm2_per_hz"]["pseudo_open_loop"])[:, 1:].mean(axis=0)
        res = np.asarray(s["psd_nm2_per_hz"]["measured_modes"])[:, 1:].mean(axis=0)
        ax.loglog(f, pol, color=f"C{i}", label=f"{name}: pseudo-open loop")
        ax.loglog(f, res, color=f"C{i}", linestyle=":", label=f"{name}: measured (residual x chi)")
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("Tip/Tilt PSD, mean of the axes [nm²/Hz]")
    ax.set_title("observed night against its simulated twin (loop run --plant)", fontsize=9)
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=7)
    save_figure(fig, OUT / "twin_night.png")
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
