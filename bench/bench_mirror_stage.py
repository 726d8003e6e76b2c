"""The mirror stage's sparse products, side by side in one run: the mirror's shape F c and the
disturbance's projection F^T d as two scipy.sparse CSR products (F, and F^T stored as its
own CSR: the loop before the core did them) against the C++ core's one pass over F
(``_core.InfluenceFunctions.shape_and_adjoint``), and F c alone through each.

Cases: both influence-function models (``[mirror] influence``) on the 80-px pupil (o = 2,
the default) and the 160-px pupil (o = 4).  Before every call a 64 MB array is written, as the
pyramid's FFTs do between two frames of the loop, so that F comes from memory as it does
there.  Calls alternate between the variants, ``--calls`` each; the table gives the median
and the 99th percentile of the wall time per call and the ratio of the medians, and checks
that both give the same numbers bit for bit.
Run:  python -m bench.bench_mirror_stage [--calls 400] [--out bench/results/mirror_stage.json]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from bench.results_file import save
from soulctl.loop.stages import core_influence
from soulctl.optics.asm import INFLUENCES, AsmGeometry
from soulctl.optics.pupil import Pupil

PUPILS = (80, 160)
EVICT_BYTES = 64 * 2**20  # more than the last-level cache


def variants(F):
    """name -> callable(c, d) of the products the mirror stage needs."""
    F_t = F.T.tocsr()
    core = core_influence(F)  # the loop's own construction of the core's copy
    return {
        "scipy F c, F^T d": lambda c, d: (F @ c, F_t @ d),
        "scipy F c only": lambda c, d: (F @ c, None),
        "core one pass": core.shape_and_adjoint,
        "core F c only": lambda c, d: (core.shape(c), None),
    }


def case_row(n_pixels: int, influence: str, calls: int) -> dict:
    F = AsmGeometry(influence=influence).sparse_influence_functions(Pupil(n_pixels))
    rng = np.random.default_rng(1)
    c, d = rng.standard_normal(F.shape[1]) * 100.0, rng.standard_normal(F.shape[0]) * 300.0
    runs = variants(F)
    reference = runs["scipy F c, F^T d"](c, d)
    shape, seen = runs["core one pass"](c, d)
    same = bool(np.array_equal(shape, reference[0]) and np.array_equal(seen, reference[1]))
    evict = np.zeros(EVICT_BYTES // 8)
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(calls):
        for name, run in runs.items():
            evict += 1.0
            t0 = time.perf_counter()
            run(c, d)
            times[name].append(time.perf_counter() - t0)
    row = {"pupil_pixels": n_pixels, "influence": influence, "n_pixels": F.shape[0], "nnz": F.nnz, "bit_equal": same}
    for name, t in times.items():
        row[name] = {"median_ms": float(np.median(t) * 1e3), "p99_ms": float(np.percentile(t, 99) * 1e3)}
    row["ratio"] = row["scipy F c, F^T d"]["median_ms"] / row["core one pass"]["median_ms"]
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--calls", type=int, default=400)
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "mirror_stage.json")
    args = p.parse_args()
    rows = [case_row(n, influence, args.calls) for n in PUPILS for influence in INFLUENCES]
    t = Table(title=f"Mirror stage's sparse products, ms per call (median / p99 of {args.calls}, F from memory)", title_justify="left")
    names = ("scipy F c, F^T d", "core one pass", "scipy F c only", "core F c only")
    for col in ("pupil", "influence", "entries", *names, "scipy / core", "bit-equal"):
        t.add_column(col, justify="left" if col in ("influence", "bit-equal") else "right")
    for r in rows:
        cells = [f"{r[v]['median_ms']:.3f} / {r[v]['p99_ms']:.3f}" for v in names]
        t.add_row(f"{r['pupil_pixels']} px", r["influence"], f"{r['nnz']:,}", *cells, f"{r['ratio']:.2f}", str(r["bit_equal"]))
    console = Console(width=160)
    console.print(t)
    save(args.out, {"benchmark": "mirror_stage", "numpy": np.__version__, "calls": args.calls, "rows": rows}, console)


if __name__ == "__main__":
    main()
