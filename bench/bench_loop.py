"""Benchmark of the simulated closed loop (`soulctl loop run`): iterations per second and the
share of time per stage, and the calibration time cold and cached.

Cases (R9.7-like photometry, seeing 1", LBT vibrations, 127 Hz resonance, noise on):
  40x40 (500 modes), 20x20 (250), 10x10 (54), modulation 3 lambda/D (24 points), at the
  default sampling (o = 2: 80-px pupil, 192^2 FFTs) and at o = 4 (160-px pupil, 4 px per
  sub-aperture, 384^2 FFTs), the sampling of the peer figure quoted in issue 5 (OOPAO: 18.5
  it/s at 160 px with 20 points and 336^2 FFTs; 36 it/s at 80 px).
  A last case at o = 4 uses the peer's 20 modulation points instead of soulctl's 24.
BLAS is limited to one thread inside ClosedLoop.run (threadpoolctl).
Stages: atmosphere, mirror (delay line, structure, F c and the disturbance's F^T d in one C++
pass, the disturbance's modes), wfs_optics (pyramid propagation), detector, slopes (C++), rtc
(C++), telemetry (the residual's modes from the disturbance's, the measured, command and
mirror modes, the recorder), metrics (PSF).
Calibration: modal basis + interaction matrix with an empty cache (cold), then from the cache.

Per frame: the median and 99th percentile of the wall time of one iteration.
Run:  python -m bench.bench_loop [--frames 300] [--out bench/results/loop.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from bench.results_file import provenance
from soulctl import __version__
from soulctl.control.gains import default_gains
from soulctl.control.structure import StructuralResonance, sampled_structure
from soulctl.disturbance.vibrations import VibrationSpectrum
from soulctl.files import atomic_write_text
from soulctl.loop.metrics import PsfAccumulator
from soulctl.loop.simulation import STAGES, ClosedLoop
from soulctl.observation import observation_for_magnitude
from soulctl.optics.atmosphere import AtmosphereConfig
from soulctl.optics.cache import ArrayCache
from soulctl.optics.calibration import BasisSetup, CalibrationSetup, calibrate
from soulctl.optics.pwfs import PyramidConfig

CASES = [
    ("40x40", 1, 500, 1700.0, None),
    ("20x20", 2, 250, 1148.0, None),
    ("10x10", 4, 54, 390.0, None),
    ("40x40 20 pts", 1, 500, 1700.0, 20),
]  # the peer's 20 modulation points (at o = 4 only)


def benchmark_loop(obs, cal) -> ClosedLoop:
    """The benchmarks' closed loop on ``cal``: seeing 1", LBT vibrations, the 127 Hz resonance
    at the observation's rate, noise on, the table's gains, seed 1."""
    structure = sampled_structure(StructuralResonance(), obs.frame_rate_hz)
    return ClosedLoop(
        obs,
        cal,
        AtmosphereConfig.lbt_default(1.0),
        default_gains(obs, structure),
        vibrations=VibrationSpectrum.lbt_default(),
        seed=1,
        structure=structure,
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--oversampling", default="2,4")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "loop.json")
    args = p.parse_args()
    rows = []
    for o in (int(x) for x in args.oversampling.split(",")):
        for label, binning, modes, rate, points in CASES:
            if points is not None and o != 4:
                continue
            obs = dataclasses.replace(observation_for_magnitude(9.7), binning=binning, modes=modes, frame_rate_hz=rate)
            setup = CalibrationSetup(PyramidConfig(binning=binning, oversampling=o, n_modulation=points), modes, BasisSetup())
            with tempfile.TemporaryDirectory() as tmp:
                cache = ArrayCache(Path(tmp))
                t0 = time.perf_counter()
                cal = calibrate(setup, cache)
                cold = time.perf_counter() - t0
                t0 = time.perf_counter()
                calibrate(setup, cache)
                cached = time.perf_counter() - t0
            loop = benchmark_loop(obs, cal)
            psf = PsfAccumulator(loop.pupil, 1.65e-6)
            loop.run(20, psf=psf)  # warm-up
            for k in loop.stage_seconds:
                loop.stage_seconds[k] = 0.0
            ends = []
            t0 = time.perf_counter()
            loop.run(args.frames, psf=psf, progress=lambda _, e=ends: e.append(time.perf_counter()))
            wall = time.perf_counter() - t0
            frame_ms = np.diff([t0] + ends) * 1e3
            stages = {k: v / args.frames * 1e3 for k, v in loop.stage_seconds.items()}
            rows.append(
                {
                    "case": label,
                    "oversampling": o,
                    "pupil_pixels": loop.pupil.n_pixels,
                    "fft_size": setup.pyramid.fft_size,
                    "modulation_points": setup.pyramid.points,
                    "valid_subapertures": loop.sensor.n_subapertures,
                    "modes": modes,
                    "iterations_per_s": args.frames / wall,
                    "ms_per_iteration": wall / args.frames * 1e3,
                    "frame_ms_median": float(np.median(frame_ms)),
                    "frame_ms_p99": float(np.percentile(frame_ms, 99)),
                    "stage_ms": stages,
                    "calibration_cold_s": cold,
                    "calibration_cached_s": cached,
                }
            )
            print(json.dumps(rows[-1]), flush=True)
    t = Table(title=f"Closed loop per iteration ({args.frames} frames per case), ms and share", title_justify="left")
    for col in ("case", "pupil/FFT/points", "it/s", "ms med/p99", *STAGES, "metrics", "cal. cold s", "cached s"):
        t.add_column(col, justify="right" if col != "case" else "left")
    for r in rows:
        total = r["ms_per_iteration"]
        t.add_row(
            r["case"],
            f"{r['pupil_pixels']}/{r['fft_size']}/{r['modulation_points']}",
            f"{r['iterations_per_s']:.1f}",
            f"{r['frame_ms_median']:.1f}/{r['frame_ms_p99']:.1f}",
            *[f"{r['stage_ms'][s]:.2f} ({100 * r['stage_ms'][s] / total:.0f}%)" for s in (*STAGES, "metrics")],
            f"{r['calibration_cold_s']:.1f}",
            f"{r['calibration_cached_s']:.2f}",
        )
    Console(width=200).print(t)
    result = {
        "benchmark": "loop",
        "soulctl": __version__,
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "numpy": np.__version__,
        "frames": args.frames,
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, json.dumps(result | provenance(), indent=1) + "\n")
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
