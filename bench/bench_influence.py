"""Cost of the mirror's influence-function model in the closed loop: the Gaussian functions
against the thin-plate cardinals (``[mirror] influence``), side by side in one run.

Cases as in ``bench_loop.py`` (R9.7-like photometry, seeing 1", LBT vibrations, 127 Hz
resonance, noise on, o = 2): 40x40 (500 modes), 20x20 (250), 10x10 (54).  For each case both
loops are built from their own calibration, then run in alternation, ``--repeats`` blocks of
``--frames`` frames each (so that other work on the machine weighs on both alike); the cost of
a block is the CPU time of the process (BLAS at one thread), the per-frame figure the median
over blocks, with the mirror stage (F c, F^T r) apart.  Also the non-zeros per pixel of the
sparse influence matrix (responses below 1e-4 of the peak dropped) and the time to build it.
Run:  python -m bench.bench_influence [--frames 100] [--repeats 5] [--out bench/results/influence.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_loop import benchmark_loop
from rich.console import Console
from rich.table import Table
from threadpoolctl import threadpool_limits

from bench.results_file import save
from soulctl.loop.simulation import ClosedLoop
from soulctl.observation import observation_for_magnitude
from soulctl.optics.asm import INFLUENCES, AsmGeometry
from soulctl.optics.cache import ArrayCache
from soulctl.optics.calibration import BasisSetup, CalibrationSetup, calibrate
from soulctl.optics.pwfs import PyramidConfig

CASES = [("40x40", 1, 500, 1700.0), ("20x20", 2, 250, 1148.0), ("10x10", 4, 54, 390.0)]


def build(label: str, binning: int, modes: int, rate: float, influence: str, cache: ArrayCache) -> tuple[ClosedLoop, dict]:
    obs = dataclasses.replace(observation_for_magnitude(9.7), binning=binning, modes=modes, frame_rate_hz=rate)
    setup = CalibrationSetup(PyramidConfig(binning=binning, oversampling=2), modes, BasisSetup(AsmGeometry(influence=influence)))
    cal = calibrate(setup, cache)
    loop = benchmark_loop(obs, cal)
    t0 = time.process_time()
    matrix = cal.basis.geometry.sparse_influence_functions(loop.pupil)
    info = {"nnz_per_pixel": matrix.nnz / matrix.shape[0], "build_s": time.process_time() - t0}
    return loop, info


def block(loop: ClosedLoop, frames: int) -> tuple[float, float]:
    """(CPU ms per frame, mirror-stage ms per frame) of ``frames`` frames."""
    before = loop.stage_seconds["mirror"]
    t0 = time.process_time()
    loop.run(frames)
    return (time.process_time() - t0) / frames * 1e3, (loop.stage_seconds["mirror"] - before) / frames * 1e3


def case_row(label, binning, modes, rate, frames, repeats, cache) -> dict:
    loops, info = {}, {}
    for influence in INFLUENCES:
        loops[influence], info[influence] = build(label, binning, modes, rate, influence, cache)
        loops[influence].run(20)  # warm-up
    ms: dict[str, list[float]] = {i: [] for i in INFLUENCES}
    mirror: dict[str, list[float]] = {i: [] for i in INFLUENCES}
    for _ in range(repeats):
        for influence in INFLUENCES:
            total, stage = block(loops[influence], frames)
            ms[influence].append(total)
            mirror[influence].append(stage)
    row = {"case": label, "modes": modes, "pupil_pixels": loops[INFLUENCES[0]].pupil.n_pixels}
    for influence in INFLUENCES:
        row[influence] = {
            "frame_ms_median": float(np.median(ms[influence])),
            "frame_ms_max": float(np.max(ms[influence])),
            "mirror_ms_median": float(np.median(mirror[influence])),
            **info[influence],
        }
    row["ratio"] = row["thin-plate"]["frame_ms_median"] / row["gaussian"]["frame_ms_median"]
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=100)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "influence.json")
    args = p.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp, threadpool_limits(1):
        cache = ArrayCache(Path(tmp))
        for case in CASES:
            rows.append(case_row(*case, args.frames, args.repeats, cache))
            print(json.dumps(rows[-1]), flush=True)
    t = Table(title=f"Closed loop per frame, CPU ms (median of {args.repeats} blocks of {args.frames} frames)", title_justify="left")
    for col in ("case", "Gaussian ms (mirror)", "thin plate ms (mirror)", "thin/Gauss", "nnz/pixel G / T", "F build s G / T"):
        t.add_column(col, justify="right" if col != "case" else "left")
    for r in rows:
        g, tp = r["gaussian"], r["thin-plate"]
        t.add_row(
            r["case"],
            f"{g['frame_ms_median']:.2f} ({g['mirror_ms_median']:.2f})",
            f"{tp['frame_ms_median']:.2f} ({tp['mirror_ms_median']:.2f})",
            f"{r['ratio']:.3f}",
            f"{g['nnz_per_pixel']:.0f} / {tp['nnz_per_pixel']:.0f}",
            f"{g['build_s']:.2f} / {tp['build_s']:.2f}",
        )
    console = Console(width=160)
    console.print(t)
    payload = {"benchmark": "influence", "numpy": np.__version__, "frames": args.frames, "repeats": args.repeats, "rows": rows}
    save(args.out, payload, console)


if __name__ == "__main__":
    main()
