"""Benchmark of the SOUL real-time path (frame -> slopes -> commands) at SOUL size.

Cases, each timed call by call with time.perf_counter_ns (warm-up, then --steps timed calls):
  core slopes (uint16), core slopes (float32)
      soulctl._core.SlopeComputer.compute(frame, out=buf): 240x240 frame, 1200 valid
      sub-apertures at binning 1 (four 40-pixel pupils, one per quadrant).
  core RTC step
      soulctl._core.RealTimeController.step(s, out=c): 2400 slopes, 672 states, 672 commands;
      Tip/Tilt with the 1700 Hz IIR of the paper (8 states each), 656 leaky integrators.
  core frame->commands     SlopeComputer.compute + RealTimeController.step (uint16 frame).
  numpy frame->commands    the same step in plain numpy with dense Lambda, Xi, Sigma (float32).
  numpy bare matvec        np.dot(A, x, out=y), A 672x2400 float32: the reference cost.
The cases are interleaved: --rounds rounds (default 10), each running every case in turn for
--steps/--rounds timed calls after 1000 untimed ones (steady state again after the other
cases' threads), so that slow phases of a shared machine fall on all cases alike; the calls of
all rounds are pooled.  A first round of 2000 calls per case is an untimed warm-up.  Inputs
cycle through a pool of 16 seeded random frames / slope vectors.  Before timing, the core and numpy
frame->commands outputs are checked to agree (float32 accuracy) from zero state.

Targets: (a) core frame->commands median <= 1.3 x numpy bare matvec median;
(b) core frame->commands p99 <= 2 x its median; (c) core frame->commands >= 1.5x faster
(median) than numpy frame->commands.

Run:  python -m bench.bench_rtc [--steps 20000] [--rounds 10] [--threads 0] [--out bench/results/rtc.json]
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from bench.results_file import provenance

try:
    import soulctl
    from soulctl import _core
except ImportError as e:  # e.g. the uncompiled source tree shadows the installed package
    sys.exit(f"cannot import soulctl._core ({e}): run with the installed package (pip install .)")
from soulctl.control.filters import Filter
from soulctl.control.rtc import build_rtc

FRAME = 240
N_SUB, N_STATES, N_CMD = 1200, 672, 672
IIR_1700 = dict(zeros=(-0.310, 0.690, 0.698, 0.705), poles=(0.042, 0.102, 0.954, 1.000), gain=0.69)
POOL = 16


def pixel_map() -> np.ndarray:
    """(1200, 4, 2) (row, col) of pupil images 1..4; x = column, y = row."""
    d = 40
    i, j = np.mgrid[0:d, 0:d]
    r2 = (i + 0.5 - d / 2) ** 2 + (j + 0.5 - d / 2) ** 2
    inside = np.flatnonzero(r2.ravel() <= (d / 2) ** 2)
    keep = np.sort(inside[np.argsort(r2.ravel()[inside], kind="stable")[:N_SUB]])  # drop outermost
    si, sj = i.ravel()[keep], j.ravel()[keep]
    centres = [(180, 180), (60, 180), (180, 60), (60, 60)]  # 1=(+x,+y) 2=(+x,-y) 3=(-x,+y) 4=(-x,-y)
    pix = np.empty((N_SUB, 4, 2), dtype=np.int64)
    for q, (rc, cc) in enumerate(centres):
        pix[:, q, 0] = rc - d // 2 + si
        pix[:, q, 1] = cc - d // 2 + sj
    return pix


def make_frames(rng, pix) -> np.ndarray:
    frames = rng.poisson(2.0, size=(POOL, FRAME, FRAME)).astype(np.uint16)  # background
    for f in frames:
        f[pix[:, :, 0], pix[:, :, 1]] = rng.poisson(100.0, size=(N_SUB, 4))
    return frames


def timed(call, inputs, n: int, warm: int) -> np.ndarray:
    """Microseconds of each of n calls call(inputs[k % POOL]), after `warm` untimed calls."""
    for k in range(warm):
        call(inputs[k % POOL])
    t = np.empty(n, dtype=np.int64)
    pc = time.perf_counter_ns
    gc.disable()
    try:
        for k in range(n):
            x = inputs[k % POOL]
            t0 = pc()
            call(x)
            t[k] = pc() - t0
    finally:
        gc.enable()
    return t / 1e3


def machine_info(rtc) -> dict:
    model = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    st = rtc.structure
    return {
        "cpu_model": model,
        "cores": os.cpu_count(),
        "usable_cores": len(os.sched_getaffinity(0)),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "soulctl": soulctl.__file__,
        "openmp": bool(_core.openmp),
        "rtc_n_threads": rtc.n_threads,
        "rtc_structure": {
            "diagonal_states": st["diagonal_states"],
            "n_blocks": len(st["block_sizes"]),
            "block_sizes": sorted(set(st["block_sizes"])),
            "input_rows": st["input_rows"],
            "output_states": st["output_states"],
        },
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=20000, help="timed calls per case (default 20000)")
    ap.add_argument("--rounds", type=int, default=10, help="interleaved rounds the calls are split into (default 10)")
    ap.add_argument("--threads", type=int, default=0, help="RTC OpenMP threads (0 = automatic)")
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results" / "rtc.json")
    args = ap.parse_args()
    warm = 2000
    rng = np.random.default_rng(20240601)
    console = Console(width=max(120, Console().width))

    # --- Slopes --------------------------------------------------------------------------
    pix = pixel_map()
    frames16 = make_frames(rng, pix)
    frames32 = frames16.astype(np.float32)
    sc = _core.SlopeComputer(pix, (FRAME, FRAME))
    sbuf = np.empty(2 * N_SUB, dtype=np.float32)

    # --- RTC: Tip, Tilt IIR + 656 leaky integrators = 672 states, 658 modes ----------------
    filters = [Filter.iir(**IIR_1700)] * 2 + [Filter.leaky(0.99, 0.4)] * (N_STATES - 16)
    n_modes = len(filters)
    R = rng.standard_normal((n_modes, 2 * N_SUB)) / np.sqrt(2 * N_SUB)
    M = rng.standard_normal((N_CMD, n_modes)) / np.sqrt(n_modes)
    mats = build_rtc(filters, R, M, state_size=N_STATES)
    assert mats.used_states == N_STATES
    rtc = mats.controller(n_threads=args.threads)
    cbuf = np.empty(N_CMD, dtype=np.float32)
    slopes = np.stack([sc.compute(f).copy() for f in frames16])

    # --- Plain numpy frame -> commands ----------------------------------------------------
    Lam, Xi, Sig = (np.ascontiguousarray(m, dtype=np.float32) for m in (mats.Lambda, mats.Xi, mats.Sigma))
    Dlt = mats.Delta.astype(np.float32)
    rows, cols = pix[:, :, 0], pix[:, :, 1]
    zeta, znew = np.zeros(N_STATES, np.float32), np.zeros(N_STATES, np.float32)
    u, c_np = np.empty(N_STATES, np.float32), np.empty(N_CMD, np.float32)

    def numpy_f2c(frame):
        nonlocal zeta, znew
        I = frame[rows, cols].astype(np.float32)
        I1, I2, I3, I4 = I[:, 0], I[:, 1], I[:, 2], I[:, 3]
        N = (I1 + I2 + I3 + I4).sum() / N_SUB
        s = np.concatenate([(I1 + I2 - I3 - I4) / N, (I1 - I2 + I3 - I4) / N])
        np.dot(Xi, s, out=u)
        np.multiply(u, Dlt, out=u)
        np.dot(Lam, zeta, out=znew)
        znew += u
        zeta, znew = znew, zeta
        np.dot(Sig, zeta, out=c_np)
        return c_np

    def core_f2c(frame):
        return rtc.step(sc.compute(frame, out=sbuf), out=cbuf)

    # --- Correctness check: both from zero state, same frames ------------------------------
    rtc.reset()
    for k in range(50):
        a, b = core_f2c(frames16[k % POOL]), numpy_f2c(frames16[k % POOL])
        if not np.allclose(a, b, rtol=1e-4, atol=1e-4 * np.max(np.abs(b))):
            sys.exit(
                f"MISMATCH at step {k}: core and numpy frame->commands differ "
                f"(max |diff| {np.max(np.abs(a - b)):.3g}, max |c| {np.max(np.abs(b)):.3g})"
            )
    console.print(f"check: core == numpy frame->commands over 50 steps (max |c| {np.max(np.abs(b)):.3g})")

    A = rng.standard_normal((N_CMD, 2 * N_SUB)).astype(np.float32)
    y = np.empty(N_CMD, np.float32)
    cases = {
        "core slopes (uint16)": (lambda f: sc.compute(f, out=sbuf), frames16),
        "core slopes (float32)": (lambda f: sc.compute(f, out=sbuf), frames32),
        "core RTC step": (lambda s: rtc.step(s, out=cbuf), slopes),
        "core frame->commands": (core_f2c, frames16),
        "numpy frame->commands": (numpy_f2c, frames16),
        "numpy bare matvec": (lambda x: np.dot(A, x, out=y), slopes),
    }
    for _name, (call, inputs) in cases.items():  # warm-up round, untimed
        timed(call, inputs, 0, warm)
    per_round = max(1, args.steps // args.rounds)
    samples = {name: [] for name in cases}
    round_medians = {name: [] for name in cases}
    for _ in range(args.rounds):
        for name, (call, inputs) in cases.items():
            t = timed(call, inputs, per_round, 1000)  # back to steady state after the other cases
            samples[name].append(t)
            round_medians[name].append(float(np.median(t)))
    res = {}
    for name, parts in samples.items():
        t = np.concatenate(parts)
        res[name] = {
            "median_us": float(np.median(t)),
            "p99_us": float(np.percentile(t, 99)),
            "mean_us": float(t.mean()),
            "min_us": float(t.min()),
            "max_us": float(t.max()),
            "round_medians_us": round_medians[name],
        }

    ref = res["numpy bare matvec"]["median_us"]
    npf = res["numpy frame->commands"]["median_us"]
    table = Table(title=f"SOUL real-time path, {per_round * args.rounds} calls/case in {args.rounds} interleaved rounds")
    for col in ("case", "median µs", "p99 µs", "mean µs", "median / bare matvec", "speed-up vs numpy f->c"):
        table.add_column(col, justify="left" if col == "case" else "right")
    for name, r in res.items():
        table.add_row(
            name,
            f"{r['median_us']:.1f}",
            f"{r['p99_us']:.1f}",
            f"{r['mean_us']:.1f}",
            f"{r['median_us'] / ref:.2f}",
            f"{npf / r['median_us']:.2f}x",
        )
    console.print(table)

    core = res["core frame->commands"]
    targets = {
        "a: core f->c median <= 1.3 x bare matvec median": (core["median_us"] / ref, 1.3, "<="),
        "b: core f->c p99 <= 2 x its median": (core["p99_us"] / core["median_us"], 2.0, "<="),
        "c: core f->c >= 1.5x faster than numpy f->c": (npf / core["median_us"], 1.5, ">="),
    }
    tout = {}
    for name, (val, lim, op) in targets.items():
        ok = val <= lim if op == "<=" else val >= lim
        tout[name] = {"value": val, "limit": lim, "pass": ok}
        console.print(f"  {'[green]PASS[/]' if ok else '[red]FAIL[/]'}  {name}: {val:.2f} (limit {op} {lim})")

    info = machine_info(rtc)
    console.print("machine: " + ", ".join(f"{k}={v}" for k, v in info.items()))

    out = {
        "args": {"steps": args.steps, "rounds": args.rounds, "threads": args.threads, "warmup": warm},
        "results": res,
        "targets": tout,
        "machine": info,
        "sizes": {
            "frame": [FRAME, FRAME],
            "subapertures": N_SUB,
            "slopes": 2 * N_SUB,
            "states": N_STATES,
            "modes": n_modes,
            "commands": N_CMD,
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=args.out.parent, prefix=".rtc-", suffix=".json.tmp")
    try:
        with os.fdopen(fd, "w") as fh:
            json.dump(out | provenance(), fh, indent=2)
        os.chmod(tmp, 0o644)  # mkstemp creates 0600
        os.replace(tmp, args.out)
    except BaseException:
        os.unlink(tmp)
        raise
    console.print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
