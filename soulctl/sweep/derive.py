"""A look-up table derived from a sweep (`soulctl sweep --derive-table`): for each simulated
magnitude, the binning and frame rate with the highest Strehl ratio; magnitudes in a row with
the same binning are merged into one table row, in the format of tables/magnitude_lut.csv
(the row's edges halfway between the simulated magnitudes, its rates the best rates at its
brightest and faintest magnitude)."""

from __future__ import annotations

import math

from .. import tables
from ..observation import BINNINGS, observation_for_magnitude

LUT_COLUMNS = ("r_min", "r_max", "binning", "subapertures", "modes", "frame_rate_max_hz", "frame_rate_min_hz", "modulation_lambda_over_d")


def best_per_magnitude(rows: list[dict]) -> list[dict]:
    """Per magnitude (ascending), the finished row with the highest Strehl ratio, its binning
    and frame rate filled in from the look-up table where the grid left them out."""
    best: dict[float, dict] = {}
    for row in rows:
        s = row.get("strehl")
        if row.get("status") != "ok" or s is None or not math.isfinite(s):
            continue
        m = float(row["magnitude"])
        if m not in best or s > best[m]["strehl"]:
            best[m] = row
    out = []
    for m in sorted(best):
        row = dict(best[m])
        obs = observation_for_magnitude(m)
        row["binning"] = row.get("binning") or obs.binning
        row["frame_rate"] = row.get("frame_rate") or obs.frame_rate_hz
        out.append(row)
    return out


def derived_table(rows: list[dict]) -> list[dict]:
    """Look-up table rows (see the module) from the sweep's rows."""
    picks = best_per_magnitude(rows)
    modes = {b.binning: b.modes for b in tables.magnitude_table()}
    out: list[dict] = []
    for i, pick in enumerate(picks):
        m = float(pick["magnitude"])
        lower = 0.0 if i == 0 else 0.5 * (float(picks[i - 1]["magnitude"]) + m)
        upper = 18.5 if i == len(picks) - 1 else 0.5 * (m + float(picks[i + 1]["magnitude"]))
        b = int(pick["binning"])
        rate = float(pick["frame_rate"])
        if out and out[-1]["binning"] == b:
            out[-1]["r_max"] = upper
            out[-1]["frame_rate_min_hz"] = rate
            out[-1]["strehl"].append(pick["strehl"])
            continue
        out.append(
            {
                "r_min": lower,
                "r_max": upper,
                "binning": b,
                "subapertures": BINNINGS[b],
                "modes": modes.get(b, 0),
                "frame_rate_max_hz": rate,
                "frame_rate_min_hz": rate,
                "modulation_lambda_over_d": 3,
                "strehl": [pick["strehl"]],
            }
        )
    return out


def lut_csv(derived: list[dict]) -> str:
    lines = ["# Look-up table derived by soulctl sweep --derive-table (best Strehl per magnitude)", ",".join(LUT_COLUMNS)]
    for r in derived:
        lines.append(",".join(f"{r[c]:g}" if isinstance(r[c], float) else str(r[c]) for c in LUT_COLUMNS))
    return "\n".join(lines) + "\n"
