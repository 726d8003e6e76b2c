"""Reading the paper's tables (tables/) with their provenance.

The files are installed with the package as ``soulctl/tables``; in a source checkout the
top-level ``tables/`` folder is used.
"""

from __future__ import annotations

import csv
import math
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from .errors import InputError
from .files import read_input_text
from .ranges import DESIGNED_GAIN, FRAME_RATE_HZ, ROOT_MODULUS, ROOTS_RATE_TOLERANCE


def tables_dir() -> Path:
    """The folder holding the tables: the installed copy, else the source tree's."""
    installed = Path(str(resources.files("soulctl"))) / "tables"
    if installed.is_dir():
        return installed
    source = Path(__file__).resolve().parent.parent / "tables"
    if source.is_dir():
        return source
    raise FileNotFoundError(f"soulctl tables not found (looked in {installed} and {source})")


def _csv_rows(text: str) -> list[dict[str, str]]:
    """Rows of a CSV text whose blank and '#' lines are comments."""
    lines = [line for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    return list(csv.DictReader(lines))


def _read_csv(name: str) -> list[dict[str, str]]:
    """A built-in table by its file name in the tables folder (never a user's path)."""
    return _csv_rows((tables_dir() / name).read_text(encoding="utf-8"))


def _read_toml(name: str) -> dict:
    """A built-in TOML table by its file name."""
    return tomllib.loads((tables_dir() / name).read_text(encoding="utf-8"))


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
    gain: float | None = None  # the gain designed with the filter (a designed table's gain column)


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


ROOT_COLUMNS = ("frame_rate_hz", *(f"zero{k}" for k in range(1, 5)), *(f"pole{k}" for k in range(1, 5)))
GAIN_COLUMN = "gain"  # optional: the paper's table has none, a designed table (filter design --out) has it


def _parse_roots(rows: list[dict[str, str]], where: str) -> tuple[IIRRoots, ...]:
    """Roots-table rows, checked: a positive rate, finite zeros, poles in -1..1, one row per rate."""
    if not rows:
        raise InputError(f"{where}: the roots table has no rows (columns: {', '.join(ROOT_COLUMNS)})")
    missing = [c for c in ROOT_COLUMNS if c not in rows[0]]
    if missing:
        raise InputError(f"{where}: the roots table lacks the columns {', '.join(missing)} (columns: {', '.join(ROOT_COLUMNS)})")
    out = []
    for i, r in enumerate(rows):
        try:
            values = [float(r[c]) for c in ROOT_COLUMNS]
        except (TypeError, ValueError):
            raise InputError(
                f"{where}: row {i + 1} of the roots table must hold 9 numbers "
                f"({', '.join(ROOT_COLUMNS)}), got {[r.get(c) for c in ROOT_COLUMNS]}"
            ) from None
        rate, zeros, poles = values[0], tuple(values[1:5]), tuple(values[5:9])
        if not (FRAME_RATE_HZ.contains(rate) and all(map(math.isfinite, values))):
            raise InputError(f"{where}: row {i + 1}: the frame rate must be in {FRAME_RATE_HZ.text()} and all roots finite")
        if not all(-1.0 <= p <= 1.0 for p in poles):
            raise InputError(f"{where}: row {i + 1}: poles must be in -1..1, got {list(poles)}")
        if not all(abs(z) <= ROOT_MODULUS for z in zeros):
            raise InputError(f"{where}: row {i + 1}: zeros must be in -{ROOT_MODULUS:g}..{ROOT_MODULUS:g}, got {list(zeros)}")
        out.append(IIRRoots(frame_rate_hz=rate, zeros=zeros, poles=poles, gain=_row_gain(r, i, where)))
    rates = [r.frame_rate_hz for r in out]
    if len(set(rates)) != len(rates):
        raise InputError(f"{where}: the roots table has two rows for one frame rate")
    return tuple(sorted(out, key=lambda r: r.frame_rate_hz))


def _row_gain(row: dict[str, str], i: int, where: str) -> float | None:
    """The row's designed gain, None where the table has no gain column (the paper's)."""
    text = row.get(GAIN_COLUMN)
    if text is None:
        return None
    try:
        gain = float(text)
    except (TypeError, ValueError):
        gain = math.nan
    if not DESIGNED_GAIN.contains(gain):
        raise InputError(f"{where}: row {i + 1}: the gain must be in {DESIGNED_GAIN.text()}, got {text!r}")
    return gain


def tt_iir_table() -> tuple[IIRRoots, ...]:
    """The Tip/Tilt IIR roots table, lowest frame rate first."""
    return _parse_roots(_read_csv("tt_iir_roots.csv"), "tables/tt_iir_roots.csv")


def nearest_roots(frame_rate_hz: float, roots: tuple[IIRRoots, ...], where: str = "the roots table") -> IIRRoots:
    """The roots-table row at the tabulated rate nearest to ``frame_rate_hz`` (ties to the
    higher); InputError if that row is more than ``ranges.ROOTS_RATE_TOLERANCE`` away from
    it (a filter designed for another rate is another filter)."""
    row = min(roots, key=lambda r: (abs(r.frame_rate_hz - frame_rate_hz), -r.frame_rate_hz))
    if abs(row.frame_rate_hz - frame_rate_hz) > ROOTS_RATE_TOLERANCE * frame_rate_hz:
        rates = ", ".join(f"{r.frame_rate_hz:g}" for r in roots)
        raise InputError(
            f"{where} has no row within {ROOTS_RATE_TOLERANCE:.0%} of {frame_rate_hz:g} Hz "
            f"(rows at {rates} Hz): give a table with a row for this rate"
        )
    return row


def read_roots_table(path: str | Path) -> tuple[IIRRoots, ...]:
    """A user roots table in the format of tables/tt_iir_roots.csv (e.g. from
    ``soulctl filter design --out``); a relative path is relative to the current folder."""
    text = read_input_text(path, "roots table")
    try:
        rows = _csv_rows(text)
    except csv.Error as e:
        raise InputError(f"cannot read roots table {path}: {e}") from None
    return _parse_roots(rows, str(path))


def delay_terms(system: str = "soul") -> dict:
    """The delay model terms of ``system`` ('soul' or 'flao') from tables/delay_model.toml."""
    data = _read_toml("delay_model.toml")
    if system not in data:
        raise InputError(f"unknown delay model '{system}': accepted {', '.join(sorted(data))}")
    return data[system]


def photometry_terms() -> dict:
    """The WFS zero point from tables/photometry.toml."""
    return _read_toml("photometry.toml")["wfs"]
