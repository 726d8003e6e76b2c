"""What several command groups share: the --config/--mag observation, the calibration cache
options, the options of a simulated loop (`loop run`, `optimize gains`), the frames progress
bar, and the two-column quantity/value table."""

from __future__ import annotations

import os
from pathlib import Path

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from .. import ranges
from ..disturbance.vibrations import VibrationSpectrum
from ..errors import InputError
from ..loop.auxloops import summary as aux_summary
from ..loop.metrics import BANDS
from ..observation import Observation, observation_for_magnitude
from ..optics.cache import ArrayCache
from .configure import parse_magnitude
from .numbers import number
from .output import console as make_console

CONFIG = typer.Option(None, "--config", metavar="FILE", help="Observation TOML (from 'soulctl configure --out').")
NO_CACHE = typer.Option(False, "--no-cache", help="Recompute and do not store (the cache is otherwise reused).")
CACHE_DIR = typer.Option(None, "--cache-dir", metavar="DIR", help="Cache folder (default $XDG_CACHE_HOME/soulctl or ~/.cache/soulctl).")


# Options of a simulated loop, shared by `loop run` and `optimize gains`.
SEEING = typer.Option(
    1.0,
    "--seeing",
    parser=number(ranges.SEEING_ARCSEC),
    metavar="ARCSEC",
    help=f"Seeing at 500 nm on the line of sight ({ranges.SEEING_ARCSEC.text()}).",
)
WIND = typer.Option(
    8.0,
    "--wind",
    parser=number(ranges.WIND_M_S),
    metavar="M/S",
    help=f"Effective wind speed of the LBT profile ({ranges.WIND_M_S.text()}).",
)
OUTER_SCALE = typer.Option(
    25.0, "--L0", parser=number(ranges.OUTER_SCALE_M), metavar="M", help=f"Outer scale ({ranges.OUTER_SCALE_M.text()})."
)
TT_CONTROL = typer.Option(None, "--tt-control", help="iir or int (default: the roots table's IIR where it has one).")
BAND = typer.Option("H", "--band", help=f"Science band of the Strehl ratio: {', '.join(BANDS)}.")
SEED = typer.Option(1, "--seed", parser=number(ranges.SEED), help=f"Seed of turbulence, vibrations and noise ({ranges.SEED.text()}).")
NO_NOISE = typer.Option(False, "--no-noise", help="Noiseless detector.")
VIBRATIONS = typer.Option(None, "--vibrations", metavar="FILE", help="Vibration lines (TOML, as tables/lbt_vibrations.toml).")
NO_VIBRATIONS = typer.Option(False, "--no-vibrations", help="No telescope vibrations.")
NO_RESONANCE = typer.Option(False, "--no-resonance", help="Without the 127 Hz structural resonance.")
OVERSAMPLING = typer.Option(
    2,
    "--oversampling",
    parser=number(ranges.OVERSAMPLING),
    help="Simulation pixels per binning-1 detector pixel (1..4; 1 only up to 90 modes).",
)
PERIOD = typer.Option(
    None,
    "--period",
    parser=number(ranges.PERIOD_S),
    metavar="S",
    help="Update period of MGM and OGTL (default: 1 s, longer where the frame rate needs it for MGM's 4 Welch "
    "segments with bins of at most 1 Hz, up to 512 frames: 2.6 s at 250 Hz, 3.3 s at 100 Hz).",
)
PROBE_MODE = typer.Option(
    30, "--probe-mode", parser=number(ranges.PROBE_MODE), help="OGTL probe mode (1-based, at most the controlled modes)."
)
PROBE_AMPLITUDE = typer.Option(
    None,
    "--probe-amplitude",
    parser=number(ranges.PROBE_AMPLITUDE_NM),
    metavar="NM",
    help=f"OGTL probe amplitude, nm peak ({ranges.PROBE_AMPLITUDE_NM.text()}; default: 20 nm, more where the "
    "WFS noise needs it for a reliable estimate, at most 80 nm).",
)
PROBE_FREQUENCY = typer.Option(
    None,
    "--probe-frequency",
    parser=number(ranges.PROBE_FREQUENCY_HZ),
    metavar="HZ",
    help=f"OGTL probe frequency (default: frame rate / 4; below Nyquist, at least {ranges.PROBE_MIN_CYCLES} cycles per --period).",
)
JSON_OUTPUT = typer.Option(False, "--json", help="Print one JSON object instead of the table.")


def check_run_options(seeing: float, wind: float, L0: float, band: str, seed: int, duration: float | None = None) -> None:
    """InputError naming the option and its accepted range for the options of a simulated loop."""
    ranges.SEEING_ARCSEC.check(seeing, "--seeing")
    ranges.WIND_M_S.check(wind, "--wind")
    ranges.OUTER_SCALE_M.check(L0, "--L0")
    ranges.SEED.check(seed, "--seed")
    if duration is not None:
        ranges.DURATION_S.check(duration, "--duration")
    if band not in BANDS:
        raise InputError(f"unknown band '{band}': accepted {', '.join(BANDS)}")


def vibration_spectrum(no_vibrations: bool, path: Path | None) -> VibrationSpectrum | None:
    """--no-vibrations, --vibrations FILE or the LBT default."""
    if no_vibrations:
        return None
    return VibrationSpectrum.read(path) if path else VibrationSpectrum.lbt_default()


def frames_progress(label: str) -> Progress:
    """A transient progress bar over frames on stderr."""
    return Progress(
        TextColumn(label),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("frames"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=make_console(stderr=True),
        transient=True,
    )


def default_cache_dir() -> Path:
    """$XDG_CACHE_HOME/soulctl, else ~/.cache/soulctl."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "soulctl"


def array_cache(no_cache: bool, cache_dir: Path | None) -> ArrayCache:
    """The calibration cache the options ask for (disabled with --no-cache)."""
    return ArrayCache(None if no_cache else (cache_dir or default_cache_dir()))


def observation_option(config: Path | None, mag: str | None) -> Observation | None:
    """The observation of --config or --mag (never both); None without either."""
    if config is not None and mag is not None:
        raise InputError("give either --config or --mag, not both")
    if config is not None:
        return Observation.read_toml(config)
    if mag is not None:
        return observation_for_magnitude(parse_magnitude(mag))
    return None


def quantity_table(title: str) -> Table:
    """A rich table with the 'quantity' and right-aligned 'value' columns of the results."""
    t = Table(title=title, title_justify="left")
    t.add_column("quantity")
    t.add_column("value", justify="right")
    return t


def aux_rows(telemetry) -> list[tuple[str, str]]:
    """Table rows of what the auxiliary loops did (``loop.auxloops.summary``)."""
    s = aux_summary({name: telemetry.aux_arrays(name) for name in telemetry.aux})
    rows = []
    if "ogtl" in s:
        o = s["ogtl"]
        rows.append(
            (
                "OGTL probe (mode, amplitude, frequency)",
                f"{o['probe_mode']}, {o['probe_amplitude_nm']:.3g} nm, {o['probe_frequency_hz']:.4g} Hz",
            )
        )
        rows.append(
            (
                "OGTL updates (k bounded to 1..k_max)",
                f"{o['updates']} (k_max {o['k_max']:.3g}): " + ", ".join(f"{n} {name}" for name, n in o["statuses"].items()),
            )
        )
    if "mgm" in s:
        rows.append(("MGM updates (noise-dominated modes, last)", f"{s['mgm']['updates']} ({s['mgm']['noise_dominated_modes_last']})"))
    if "safety" in s:
        f = s["safety"]
        rows.append(
            ("safety net: restores of the last good gains and k", f"{f['restores']}" + (" (could not recover)" if f["gave_up"] else ""))
        )
    return rows
