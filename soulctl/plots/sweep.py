"""The picture an AO scientist expects of a sweep: Strehl ratio versus guide-star magnitude,
one curve per seeing (and per binning where the grid varies it); where other parameters vary
too (frame rate, wind, seed, ...), each point is the best Strehl over them."""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path

from .figure import new_figure, save_figure


def strehl_vs_magnitude(rows: list[dict], path: Path) -> Path:
    best: defaultdict[str, dict] = defaultdict(dict)  # label -> magnitude -> best Strehl
    binnings = {r.get("binning") for r in rows}
    for r in rows:
        if r.get("status") == "ok" and r.get("strehl") is not None and math.isfinite(r["strehl"]):
            label = f'seeing {r["seeing"]:g}"' + (f", binning {r['binning']}" if len(binnings) > 1 else "")
            m = float(r["magnitude"])
            best[label][m] = max(best[label].get(m, 0.0), float(r["strehl"]))
    curves = {label: sorted(points.items()) for label, points in best.items()}
    fig = new_figure()
    ax = fig.subplots()
    for label, points in sorted(curves.items()):
        ax.plot([m for m, _ in points], [s for _, s in points], "o-", label=label, markersize=4)
    band = next((r.get("band") for r in rows if r.get("band")), "H")
    ax.set_xlabel("guide star R magnitude")
    ax.set_ylabel(f"Strehl ratio ({band})")
    ax.set_ylim(bottom=0)
    ax.grid(True, alpha=0.25)
    if curves:
        ax.legend(fontsize=8)
    ax.set_title("Simulated Strehl ratio versus magnitude", fontsize=10)
    save_figure(fig, path)
    return path
