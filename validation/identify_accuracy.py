"""Accuracy of `soulctl telemetry identify` on simulated telemetry whose truth is known.

Each case runs `soulctl loop run --telemetry` (one of the paper's operating points, a seed,
with or without OGTL and its probe mode), identifies it, and compares with the truth:

* delay: the simulated delay (the record's delay_frames);
* chi: with a probe on mode p, the probe's chi is the dynamic optical gain of p (exact,
  M/C = -chi z^-d); compared with the rejection fit's value of the group holding p;
* noise: the detector noise propagated to the modes (``WavefrontSensor.modal_noise_nm``, k = 1);
* seeing: the run's;
* vibration lines: the realised RMS of each simulated line over the identification window,
  its series regenerated from the run's seed (``VibrationSource.next_lines`` in the loop's blocks).

One JSON line per case in validation/results/identify_accuracy.jsonl (appended; cases already
there are skipped).  Usage:

    python -m validation.identify_accuracy [--quick] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from soulctl.disturbance.vibrations import VibrationSource, VibrationSpectrum
from soulctl.loop.run import calibration_for
from soulctl.loop.simulation import _photons_per_frame
from soulctl.loop.stages import VIBRATION_BLOCK
from soulctl.optics.cache import ArrayCache
from soulctl.optics.detector import Detector
from soulctl.optics.pwfs import Pyramid
from soulctl.optics.sensor import WavefrontSensor
from soulctl.run_config import read_run_config
from validation.provenance import provenance

ROOT = Path(__file__).resolve().parent.parent
CASES = [
    # (name, example, seed, probe mode or None, duration s)
    ("R13", "paper_r13_980hz.toml", 1, None, 10),
    ("R13", "paper_r13_980hz.toml", 1, 5, 10),
    ("R13", "paper_r13_980hz.toml", 1, 30, 10),
    ("R13", "paper_r13_980hz.toml", 1, 200, 10),
    ("R13", "paper_r13_980hz.toml", 2, None, 10),
    ("R13", "paper_r13_980hz.toml", 2, 100, 10),
    ("R9.7", "paper_r9.7_1700hz.toml", 1, None, 10),
    ("R9.7", "paper_r9.7_1700hz.toml", 1, 30, 10),
    ("R9.7", "paper_r9.7_1700hz.toml", 2, 300, 10),
    ("R13", "paper_r13_980hz.toml", 3, None, 60),
]


def case_id(case) -> str:
    name, _, seed, probe, duration = case
    return f"{name}-s{seed}-{'probe' + str(probe) if probe else 'noprobe'}-{duration}s"


def _run(case, workdir: Path) -> tuple[Path, dict]:
    """The case's telemetry (simulated unless ``workdir`` holds it from an earlier run) and its identification."""
    name, example, seed, probe, duration = case
    tel = workdir / f"{case_id(case)}.h5"
    cmd = ["soulctl", "loop", "run", "--config", str(ROOT / "examples" / example), "--duration", str(duration), "--seed", str(seed)]
    cmd += ["--telemetry", str(tel), "--json"]
    if probe:
        cmd += ["--ogtl", "--probe-mode", str(probe)]
    if not tel.exists():
        subprocess.run(cmd, check=True, capture_output=True, cwd=workdir)
    ident = subprocess.run(["soulctl", "telemetry", "identify", str(tel), "--json"], check=True, capture_output=True, cwd=workdir)
    return tel, json.loads(ident.stdout)


def _realised_lines(config, first: int, frames: int) -> list[dict]:
    obs = config.observation
    rng = np.random.default_rng(config.seed)
    _, vib_seed, _ = rng.integers(0, 2**63, size=3)
    spectrum, _ = VibrationSpectrum.lbt_default().below_nyquist(obs.frame_rate_hz)
    source = VibrationSource(spectrum, obs.frame_rate_hz, np.random.default_rng(vib_seed))
    total = first + frames
    blocks = [source.next_lines(VIBRATION_BLOCK) for _ in range(total // VIBRATION_BLOCK + 1)]
    x = np.concatenate(blocks, axis=1)[:, first:total]
    rms = np.sqrt(np.mean(x**2, axis=1))
    return [{"frequency_hz": ln.frequency_hz, "tip_mas": float(r[0]), "tilt_mas": float(r[1])} for ln, r in zip(spectrum.lines, rms)]


def _noise_truth(config) -> np.ndarray:
    cal = calibration_for(config.request(), ArrayCache(Path.home() / ".cache" / "soulctl"))
    pyramid = Pyramid(cal.setup.pyramid)
    sensor = WavefrontSensor(pyramid, Detector(), _photons_per_frame(config.observation, pyramid.pupil))
    return sensor.modal_noise_nm(cal.reconstructor) ** 2


def _group_of(groups: list[dict], mode: int) -> dict:
    for g in groups:
        lo, hi = (int(x) for x in g["modes"].split("-"))
        if lo <= mode <= hi:
            return g
    raise ValueError(mode)


def evaluate(case, tel: Path, ident: dict) -> dict:
    name, _, seed, probe, duration = case
    config = read_run_config(tel)
    noise = _noise_truth(config)
    fitted = np.array([np.nan if x is None else x for x in ident["noise_nm2"]])
    ratio = fitted / noise
    groups = [(lo, hi) for lo, hi in ((3, 9), (10, 29), (30, 89), (90, 269), (270, 500)) if lo <= len(noise)]
    row = {
        "case": case_id(case),
        "point": name,
        "seed": seed,
        "probe_mode": probe,
        "duration_s": duration,
        "window_s": ident["window"]["seconds"],
        "delay": ident["delay_frames"]["value"],
        "delay_sigma": ident["delay_frames"]["sigma"],
        "delay_true": ident["delay_frames"]["recorded"],
        "chi_groups": ident["rejection_fit_chi"],
        "noise_ratio_groups": {f"{lo}-{hi}": float(np.nanmedian(ratio[lo - 1 : min(hi, len(noise))])) for lo, hi in groups},
        "noise_ratio_tip_tilt": float(np.mean(ratio[:2])),
        "seeing": ident["turbulence"]["seeing_arcsec"],
        "seeing_true": config.atmosphere.seeing_arcsec,
        "L0": ident["turbulence"]["L0_m"],
        "L0_true": config.atmosphere.L0_m,
        "lines": ident["vibration_lines"],
        "lines_window_s": ident["lines_window"]["frames"] / config.observation.frame_rate_hz,
        "lines_true": _realised_lines(config, ident["lines_window"]["first_frame"], ident["lines_window"]["frames"]),
        "identify_s": max(ident["seconds"].values()),  # cumulative clock
    }
    if probe:
        group = _group_of(ident["rejection_fit_chi"], probe)
        row |= {"chi_probe": ident["probe"]["chi"]["value"], "chi_probe_sigma": ident["probe"]["chi"]["sigma"], "chi_group_of_probe": group}
    return row


def table(rows: list[dict]) -> str:
    """The closing note's table: one row per case."""
    out = [
        "| case | window s | delay (true) | chi: probe / its group's fit | noise fit/true, groups | TT noise | seeing (true) "
        "| lines >= 3 mas: f, RMS found/realised |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        chi = "-"
        if r.get("probe_mode"):
            g = r["chi_group_of_probe"]
            chi = f"mode {r['probe_mode']}: {r['chi_probe']:.3f} / {g['value']:.3f} ({g['value'] / r['chi_probe'] - 1:+.0%})"
        noise = ", ".join(f"{v:.2f}" for v in r["noise_ratio_groups"].values())
        lines = []
        for true in r["lines_true"]:
            for axis in ("tip_mas", "tilt_mas"):
                if true[axis] < 3.0:
                    continue
                found = [x for x in r["lines"] if abs(x["frequency_hz"]["value"] - true["frequency_hz"]) < 1.0]
                if not found:
                    lines.append(f"{true['frequency_hz']:g} Hz {axis[:-4]}: not found")
                    continue
                x, rms = found[0], found[0][axis]["value"]
                lines.append(f"{x['frequency_hz']['value']:.2f} Hz {axis[:-4]} {rms:.2f}/{true[axis]:.2f} ({rms / true[axis] - 1:+.0%})")
        out.append(
            f"| {r['case']} | {r['window_s']:.1f} | {r['delay']:.3f} ({r['delay_true']:.3f}) | {chi} | {noise} | "
            f"{r['noise_ratio_tip_tilt']:.2f} | {r['seeing']:.3f} ({r['seeing_true']:g}) | {'; '.join(lines)} |"
        )
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=str(ROOT / "validation" / "results" / "identify_accuracy.jsonl"))
    ap.add_argument("--quick", action="store_true", help="the first case only")
    ap.add_argument(
        "--keep", default=str(Path(tempfile.gettempdir()) / "soulctl-identify-validation"), help="folder of the simulated records (reused)"
    )
    ap.add_argument("--table", action="store_true", help="print the results' table and exit")
    args = ap.parse_args()
    out = Path(args.out)
    if args.table:
        print(table([json.loads(x) for x in out.read_text().splitlines()]))
        return
    done = {json.loads(x)["case"] for x in out.read_text().splitlines()} if out.exists() else set()
    keep = Path(args.keep)
    keep.mkdir(parents=True, exist_ok=True)
    for case in CASES[:1] if args.quick else CASES:
        if case_id(case) in done:
            continue
        t0 = time.perf_counter()
        tel, ident = _run(case, keep)
        row = evaluate(case, tel, ident) | {"wall_s": time.perf_counter() - t0} | provenance()
        with out.open("a") as f:
            f.write(json.dumps(row) + "\n")
        print(row["case"], "delay", round(row["delay"], 3), row["delay_true"], "seeing", round(row["seeing"], 3), flush=True)


if __name__ == "__main__":
    main()
