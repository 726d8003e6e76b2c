"""Benchmark of the PWFS measurement: propagation with modulation + detector + slopes, per frame.

Cases, run side by side in one process, on turbulent wavefronts (the LBT profile at seeing
0.8", frozen flow at 1700 Hz), modulation 3 lambda/D (24 points):
  binning b, oversampling o   the library's path (soulctl.optics.sensor.WavefrontSensor.slopes
                              with a noisy detector): propagation, detector, C++ slopes, total.
                              b = 1..4 (40/20/13/10 sub-apertures across) at o = 2 (default) and 1.
  alternatives at b = 1, o = 2, propagation only:
    workers=1                 the same FFTs on one thread;
    complex128 numpy.fft      no scipy.fft, double precision;
    tilt-in-pupil modulation  the textbook way: for each modulation point a tilted pupil field,
                              a forward FFT, the pyramid mask, an inverse FFT (2 FFTs per point
                              instead of 1 + 1 per point);
    band of 3 wavelengths     the polychromatic beam (``band_nm`` 658, 775, 892 nm; 28, 24, 24
                              modulation points): what a band costs over the monochromatic model.
Frames are timed one by one, cases interleaved in rounds; median and p99 per frame.

Run:  python -m bench.bench_pwfs [--frames 60] [--rounds 5] [--out bench/results/pwfs.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import scipy.fft
from rich.console import Console
from rich.table import Table

from bench.results_file import provenance
from soulctl import __version__
from soulctl.files import atomic_write_text
from soulctl.optics.atmosphere import AtmosphereConfig, FrozenFlowAtmosphere
from soulctl.optics.detector import Detector
from soulctl.optics.pwfs import Pyramid, PyramidConfig
from soulctl.optics.sensor import WavefrontSensor


def screens(pupil, n: int, seed: int = 1) -> np.ndarray:
    """n frames at 1700 Hz of the LBT profile (seeing 0.8", v_eff 8 m/s), OPD in nm."""
    atm = FrozenFlowAtmosphere(AtmosphereConfig.lbt_default(0.8), pupil.n_pixels, pupil.pixel_scale_m, seed)
    return np.stack([atm.opd_nm(k / 1700.0) * pupil.mask for k in range(n)]).astype(np.float32)


def tilt_in_pupil(pyr: Pyramid):
    """Propagation with the modulation as a tilt of the pupil field (2 FFTs per point)."""
    c = pyr.config
    N, n_pup = c.fft_size, pyr.pupil.n_pixels
    o = (N - n_pup) // 2
    f = np.fft.fftfreq(N, 1.0 / N)
    shift = 1.2 * n_pup / 2
    mask = np.exp(1j * (-2 * np.pi * np.abs(f[:, None] + 0.5) * shift / N - 2 * np.pi * np.abs(f[None, :] + 0.5) * shift / N)).astype(
        np.complex64
    )
    x = np.arange(N)
    r = c.modulation_lambda_over_d * N / n_pup
    angles = 2 * np.pi * np.arange(c.points) / c.points
    tilts = np.stack([np.exp(2j * np.pi * (r * np.cos(a) * x[None, :] + r * np.sin(a) * x[:, None]) / N) for a in angles]).astype(
        np.complex64
    )
    amp = np.zeros((N, N), np.complex64)
    amp[o : o + n_pup, o : o + n_pup] = pyr._amplitude
    k = 2 * np.pi / (c.wavelength_m * 1e9)

    def run(opd):
        field = amp.copy()
        field[o : o + n_pup, o : o + n_pup] *= np.exp(1j * k * opd).astype(np.complex64)
        focal = scipy.fft.fft2(field * tilts, workers=-1)
        images = scipy.fft.ifft2(focal * mask, workers=-1, overwrite_x=True)
        return np.sum(images.real**2 + images.imag**2, axis=0)

    return run


def numpy128(pyr: Pyramid):
    c = pyr.config
    N, n_pup = c.fft_size, pyr.pupil.n_pixels
    o = (N - n_pup) // 2
    masks = pyr._masks.astype(np.complex128)
    amp = pyr._amplitude.astype(np.complex128)
    k = 2 * np.pi / (c.wavelength_m * 1e9)

    def run(opd):
        field = np.zeros((N, N), np.complex128)
        field[o : o + n_pup, o : o + n_pup] = amp * np.exp(1j * k * opd)
        images = np.fft.ifft2(np.fft.fft2(field) * masks)
        return np.sum(np.abs(images) ** 2, axis=0)

    return run


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=60, help="timed frames per case and round")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "pwfs.json")
    args = p.parse_args()

    cases = []  # (name, meta, callables per part)
    for o in (2, 1):
        for b in (1, 2, 3, 4):
            cfg = PyramidConfig(binning=b, oversampling=o)
            wfs = WavefrontSensor(Pyramid(cfg), Detector(), photons_per_frame=25000.0)
            opds = screens(wfs.pupil, args.frames)
            cases.append(
                (
                    f"b{b} o{o}",
                    {
                        "binning": b,
                        "oversampling": o,
                        "subapertures_across": {1: 40, 2: 20, 3: 13, 4: 10}[b],
                        "valid_subapertures": wfs.n_subapertures,
                        "pupil_pixels": wfs.pupil.n_pixels,
                        "fft_size": cfg.fft_size,
                        "frame": list(cfg.frame_shape),
                        "modulation_points": cfg.points,
                    },
                    wfs,
                    opds,
                )
            )
    base = cases[0][2]
    alt_opds = cases[0][3]
    one_thread = Pyramid(PyramidConfig(binning=1, oversampling=2), workers=1)
    alternatives = [
        ("b1 o2 workers=1", one_thread.intensity),
        ("b1 o2 complex128 numpy.fft", numpy128(base.pyramid)),
        ("b1 o2 tilt-in-pupil modulation", tilt_in_pupil(base.pyramid)),
        ("b1 o2 band of 3 wavelengths", Pyramid(PyramidConfig(binning=1, oversampling=2, band_nm=(658.0, 775.0, 892.0))).intensity),
    ]

    rng = np.random.default_rng(0)
    times: dict[str, dict[str, list[float]]] = {}
    for _ in range(args.rounds):
        for name, _meta, wfs, opds in cases:
            t = times.setdefault(name, {"propagation": [], "detector": [], "slopes": [], "total": []})
            wfs.slopes(opds[0], rng)  # warm
            for opd in opds:
                t0 = time.perf_counter()
                intensity = wfs.pyramid.intensity(opd)
                t1 = time.perf_counter()
                frame = wfs.detector.read(intensity, wfs.photons_per_frame, rng)
                t2 = time.perf_counter()
                wfs.slopes_of_frame(frame)
                t3 = time.perf_counter()
                for part, dt in zip(("propagation", "detector", "slopes", "total"), (t1 - t0, t2 - t1, t3 - t2, t3 - t0)):
                    t[part].append(dt)
        for name, fn in alternatives:
            t = times.setdefault(name, {"propagation": []})
            fn(alt_opds[0])
            for opd in alt_opds:
                t0 = time.perf_counter()
                fn(opd)
                t["propagation"].append(time.perf_counter() - t0)

    def stats(x):
        x = np.array(x) * 1e3
        return {"median_ms": float(np.median(x)), "p99_ms": float(np.percentile(x, 99))}

    rows = []
    ref = np.median(times["b1 o2"]["propagation"])
    for name, meta, _, _ in cases:
        rows.append({"case": name, **meta, **{part: stats(v) for part, v in times[name].items()}})
    for name, _ in alternatives:
        rows.append(
            {
                "case": name,
                "propagation": stats(times[name]["propagation"]),
                "ratio_to_library": float(np.median(times[name]["propagation"]) / ref),
            }
        )

    t = Table(title=f"PWFS measurement per frame, modulation 3 λ/D ({args.rounds}×{args.frames} frames per case)", title_justify="left")
    for col in (
        "case",
        "sub-ap.",
        "pupil/FFT px",
        "propagation ms (p99)",
        "detector ms",
        "slopes ms",
        "total ms (p99)",
        "frames/s",
        "vs library",
    ):
        t.add_column(col, justify="right" if col != "case" else "left")
    for r in rows:
        if "total" in r:
            t.add_row(
                r["case"],
                f"{r['subapertures_across']} ({r['valid_subapertures']})",
                f"{r['pupil_pixels']}/{r['fft_size']}",
                f"{r['propagation']['median_ms']:.2f} ({r['propagation']['p99_ms']:.2f})",
                f"{r['detector']['median_ms']:.3f}",
                f"{r['slopes']['median_ms']:.3f}",
                f"{r['total']['median_ms']:.2f} ({r['total']['p99_ms']:.2f})",
                f"{1e3 / r['total']['median_ms']:.0f}",
                "",
            )
        else:
            t.add_row(
                r["case"],
                "40",
                "80/192",
                f"{r['propagation']['median_ms']:.2f} ({r['propagation']['p99_ms']:.2f})",
                "",
                "",
                "",
                "",
                f"{r['ratio_to_library']:.2f}×",
            )
    Console(width=160).print(t)
    result = {
        "benchmark": "pwfs",
        "soulctl": __version__,
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "frames": args.frames,
        "rounds": args.rounds,
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, json.dumps(result | provenance(), indent=1) + "\n")
    print(f"written {args.out}")


if __name__ == "__main__":
    main()
