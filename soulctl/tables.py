"""Reading the paper's tables (tables/) with their provenance.

The files are installed with the package as ``soulctl/tables``; in a source checkout the
top-level ``tables/`` folder is used.
"""

from __future__ import annotations

import csv
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from .errors import InputError


def tables_dir() -> Path:
    """The folder holding the tables: the installed copy, else the source tree's."""
    installed = Path(str(resources.files("soulctl"))) / "tables"
    if installed.is_dir():
        return installed
    source = Path(__file__).resolve().parent.parent / "tables"
    if source.is_dir():
        return source
    raise FileNotFoundError("soulctl tables not found (looked in %s and %s)" % (installed, source))


def _read_csv(name: str) -> list[dict[str, str]]:
    path = tables_dir() / name
    with open(path, newline="") as f:
        lines = [line for line in f if line.strip() and not line.lstrip().startswith("#")]
    return list(csv.DictReader(lines))


def _read_toml(name: str) -> dict:
    with open(tables_dir() / name, "rb") as f:
        return tomllib.load(f)


@dataclass(frozen=True)
class MagnitudeBand:
    """One row of the magnitude look-up table (paper, Tab. params): applies to r_min < R <= r_max."""

    r_min: float
    r_max: float
    binning: int
    subapertures: int
    modes: int
    frame_rate_max_hz: float
    frame_rate_min_hz: float
    modulation_lambda_over_d: float

    def contains(self, magnitude: float, first: bool = False) -> bool:
        lower_ok = magnitude >= self.r_min if first else magnitude > self.r_min
        return lower_ok and magnitude <= self.r_max

    def label(self, first: bool = False) -> str:
        """The row's range as the paper writes it (the first row is closed at both ends)."""
        return f"{self.r_min:g} <= R <= {self.r_max:g}" if first else f"{self.r_min:g} < R <= {self.r_max:g}"


@dataclass(frozen=True)
class IIRRoots:
    """Zeros and poles of a Tip/Tilt IIR filter at one frame rate (paper, Tab. roots)."""

    frame_rate_hz: float
    zeros: tuple[float, ...]
    poles: tuple[float, ...]


MAGNITUDE_SOURCE = "Agapito et al. 2021, Tab. 'Summary of SOUL parameters'"
ROOTS_SOURCE = "Agapito et al. 2021, Tab. 'Zeros and poles of the IIR filters'"


def magnitude_table() -> tuple[MagnitudeBand, ...]:
    """The magnitude look-up table, brightest row first."""
    rows = [
        MagnitudeBand(
            r_min=float(r["r_min"]),
            r_max=float(r["r_max"]),
            binning=int(r["binning"]),
            subapertures=int(r["subapertures"]),
            modes=int(r["modes"]),
            frame_rate_max_hz=float(r["frame_rate_max_hz"]),
            frame_rate_min_hz=float(r["frame_rate_min_hz"]),
            modulation_lambda_over_d=float(r["modulation_lambda_over_d"]),
        )
        for r in _read_csv("magnitude_lut.csv")
    ]
    return tuple(sorted(rows, key=lambda b: b.r_min))


def magnitude_range(bands: tuple[MagnitudeBand, ...]) -> tuple[float, float]:
    return bands[0].r_min, bands[-1].r_max


def band_for_magnitude(magnitude: float, bands: tuple[MagnitudeBand, ...]) -> MagnitudeBand:
    """The table row that applies to an R magnitude; InputError outside the table."""
    for i, band in enumerate(bands):
        if band.contains(magnitude, first=(i == 0)):
            return band
    lo, hi = magnitude_range(bands)
    raise InputError(f"R magnitude {magnitude:.10g} is outside the look-up table: accepted range {lo:g} <= R <= {hi:g}")


def tt_iir_table() -> tuple[IIRRoots, ...]:
    """The Tip/Tilt IIR roots table, lowest frame rate first."""
    rows = []
    for r in _read_csv("tt_iir_roots.csv"):
        rows.append(
            IIRRoots(
                frame_rate_hz=float(r["frame_rate_hz"]),
                zeros=tuple(float(r[f"zero{k}"]) for k in range(1, 5)),
                poles=tuple(float(r[f"pole{k}"]) for k in range(1, 5)),
            )
        )
    return tuple(sorted(rows, key=lambda r: r.frame_rate_hz))


def delay_terms(system: str = "soul") -> dict:
    """The delay model terms of ``system`` ('soul' or 'flao') from tables/delay_model.toml."""
    data = _read_toml("delay_model.toml")
    if system not in data:
        raise InputError(f"unknown delay model '{system}': accepted {', '.join(sorted(data))}")
    return data[system]


def photometry_terms() -> dict:
    """The WFS zero point from tables/photometry.toml."""
    return _read_toml("photometry.toml")["wfs"]
