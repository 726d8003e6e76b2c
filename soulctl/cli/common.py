"""What several command groups share: the --config/--mag observation, the calibration cache
options, the options of a simulated loop (`loop run`, `optimize gains`), the frames progress
bar, and the two-column quantity/value table."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Protocol

import typer
from rich.table import Table

from .. import defaults, ranges
from ..control.gains import DEFAULT_FORGETTING, SUFFIXES, LoopGains, read_gain_file
from ..control.ogtl import PROBE_MODE as PROBE_MODE_DEFAULT
from ..errors import InputError
from ..loop.auxloops import summary as aux_summary
from ..loop.metrics import BANDS
from ..observation import TT_CONTROLS, Observation, observation_for_magnitude
from ..offline.recorded import STRUCTURE_CHOICES
from ..optics.cache import ArrayCache
from ..ranges import LOOP_GAIN, MAGNIFICATION, ROTATION_DEG, SHIFT_PITCH
from ..run_config import REGISTRATION_KEYS, RunConfig, read_run_config
from . import output, quick
from .numbers import number, parse_magnitude

RUN_CONFIG = typer.Option(
    None,
    "--config",
    metavar="FILE",
    help="Run description (TOML, as --print-config prints it; an observation file from 'soulctl configure --out' is one) "
    "or a telemetry file (.h5) whose run is repeated; the other options override its fields.",
)
MISREGISTRATION = typer.Option(
    None,
    "--misregistration",
    metavar="DX,DY[,ROT[,MAG]]",
    help="The mirror on the pyramid against the calibration: shift in actuator pitches, rotation (deg), magnification.",
)
NO_CACHE = typer.Option(False, "--no-cache", help="Recompute and do not store (the cache is otherwise reused).")
CACHE_DIR = typer.Option(None, "--cache-dir", metavar="DIR", help="Cache folder (default $XDG_CACHE_HOME/soulctl or ~/.cache/soulctl).")


# The turbulence's options, declared once for every command that takes them (`loop run`,
# `optimize gains`, `filter design`, `optics`): one help text, the range checked by the parser;
# ``default`` None makes the option an override of the run description's (else soulctl.defaults).
def _turbulence_option(flag: str, accepted: ranges.Range, metavar: str, run_default: float, what: str, default: float | None):
    return typer.Option(
        default,
        flag,
        parser=number(accepted, flag),
        metavar=metavar,
        show_default=str(run_default) if default is None else True,
        help=f"{what} ({accepted.text()}).",
    )


def seeing_option(default: float | None = None):
    return _turbulence_option(
        "--seeing", ranges.SEEING_ARCSEC, "ARCSEC", defaults.SEEING_ARCSEC, "Seeing at 500 nm on the line of sight", default
    )


def wind_option(default: float | None = None):
    return _turbulence_option(
        "--wind", ranges.WIND_M_S, "M/S", defaults.WIND_M_S, "Effective (5/3-moment) wind speed of the LBT profile", default
    )


def outer_scale_option(default: float | None = None):
    return _turbulence_option("--L0", ranges.OUTER_SCALE_M, "M", defaults.L0_M, "Outer scale of the von Kármán turbulence", default)


# Options of a simulated loop, shared by `loop run` and `optimize gains`: each an override of a
# field of the run description (None: the description's value, else soulctl.defaults).
SEEING = seeing_option()
WIND = wind_option()
OUTER_SCALE = outer_scale_option()
TT_CONTROL = typer.Option(
    None, "--tt-control", metavar="|".join(TT_CONTROLS), help="Tip/Tilt controller (default: the roots table's IIR where it has one)."
)
BAND = typer.Option(None, "--band", metavar="|".join(BANDS), show_default=defaults.BAND, help="Science band of the Strehl ratio.")
SEED = typer.Option(
    None,
    "--seed",
    parser=number(ranges.SEED),
    show_default=str(defaults.SEED),
    help=f"Seed of turbulence, vibrations and noise ({ranges.SEED.text()}).",
)
NO_NOISE = typer.Option(False, "--no-noise", help="Noiseless detector.")
VIBRATIONS = typer.Option(
    None,
    "--vibrations",
    metavar="FILE|NAME",
    help="Vibration lines (TOML, as tables/lbt_vibrations.toml), or a profile: lbt (default), lbt-onsky.",
)
NO_VIBRATIONS = typer.Option(False, "--no-vibrations", help="No telescope vibrations.")
RECORD_DELAY = typer.Option(
    None,
    "--delay-frames",
    parser=number(ranges.DELAY_FRAMES),
    metavar="D",
    help="The loop delay in frames where the record has none, or to replace its own (`telemetry identify` estimates it).",
)
NO_RESONANCE = typer.Option(False, "--no-resonance", help="Without the 127 Hz structural resonance.")
RESONANCE = typer.Option(
    "auto",
    "--resonance",
    metavar="auto|lbt|none",
    help="The 127 Hz structural resonance in a record's model: auto (its run's; LBT's for LBT's adaptive secondary), lbt or none.",
)
OVERSAMPLING = typer.Option(
    None,
    "--oversampling",
    parser=number(ranges.OVERSAMPLING),
    show_default=str(defaults.OVERSAMPLING),
    help="Simulation pixels per binning-1 detector pixel (1..4; 1 only up to 90 modes).",
)
WFS_FIELD = typer.Option(
    None,
    "--wfs-field",
    parser=number(ranges.WFS_FIELD_OF_VIEW_ARCSEC),
    metavar="ARCSEC",
    show_default=f"{defaults.WFS_FIELD_ARCSEC:g}",
    help=f"The pyramid's simulated field of view, a diameter ({ranges.WFS_FIELD_OF_VIEW_ARCSEC.text()}; SOUL's "
    f"{defaults.WFS_FIELD_ARCSEC:g}\" with a stop at its edge; 0: the field the pupil's sampling gives, no stop, "
    "~2x faster at oversampling 2).",
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
    None,
    "--probe-mode",
    show_default=str(PROBE_MODE_DEFAULT),
    parser=number(ranges.PROBE_MODE),
    help="OGTL probe mode (1-based, at most the controlled modes).",
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
JSON_OUTPUT = output.JSON_OUTPUT


def check_resonance(choice: str) -> str:
    """--resonance: one of recorded.STRUCTURE_CHOICES (InputError naming them)."""
    if choice not in STRUCTURE_CHOICES:
        raise InputError(f"--resonance must be one of {', '.join(STRUCTURE_CHOICES)}, got {choice!r}")
    return choice


def parse_gains(text: str | None, forgetting: float) -> LoopGains | None:
    """``TT,MID,HIGH`` (the paper's three groups) or a per-mode gain file
    (``control.gains``: TOML ``gains = [...]``, or text/CSV lines)."""
    if text is None:
        return None
    path = _gain_file(text)
    if path is not None:
        return LoopGains.from_modes(read_gain_file(path), forgetting)
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 3 or not all(LOOP_GAIN.contains(v) for v in values):
        raise InputError(f"--gains must be TT,MID,HIGH (three numbers in {LOOP_GAIN.text()}) or a gain file, got '{text}'")
    tip_tilt, mid, high = values
    return LoopGains(tip_tilt, mid, high, forgetting=forgetting)


def gain_overrides(text: str | None) -> dict:
    """--gains as an override of the run description: control.gains (the three groups) or
    control.mode_gains (a gain file)."""
    g = parse_gains(text, DEFAULT_FORGETTING)
    if g is None:
        return {}
    return {"control.mode_gains": list(g.modes)} if g.modes is not None else {"control.gains": [g.tip_tilt, g.mid, g.high]}


def _gain_file(text: str) -> Path | None:
    """--gains as a gain file (a gain file's suffix, or an existing path), else None (groups)."""
    path = Path(text)
    return path if path.suffix.lower() in SUFFIXES or path.exists() else None


def gain_file_input(text: str | None) -> tuple[str, Path | None]:
    """--gains as an input file of the command (for the output checks), or None."""
    return ("--gains", None if text is None else _gain_file(text))


def check_run_options(seeing, wind, L0, band, seed, duration=None, oversampling=None, wfs_field=None) -> None:
    """InputError naming the option and its accepted range for the options of a simulated loop
    (None: not given)."""
    for value, accepted, option in (
        (seeing, ranges.SEEING_ARCSEC, "--seeing"),
        (wind, ranges.WIND_M_S, "--wind"),
        (L0, ranges.OUTER_SCALE_M, "--L0"),
        (seed, ranges.SEED, "--seed"),
        (duration, ranges.DURATION_S, "--duration"),
        (oversampling, ranges.OVERSAMPLING, "--oversampling"),
        (wfs_field, ranges.WFS_FIELD_OF_VIEW_ARCSEC, "--wfs-field"),
    ):
        if value is not None:
            accepted.check(value, option)
    if band is not None and band not in BANDS:
        raise InputError(f"unknown band '{band}': accepted {', '.join(BANDS)}")


class LoopOptions(Protocol):
    """The options of a simulated loop that `loop run` and `optimize gains` share (read-only:
    the commands' option tables are frozen)."""

    @property
    def seeing(self) -> float | None: ...
    @property
    def wind(self) -> float | None: ...
    @property
    def L0(self) -> float | None: ...
    @property
    def tt_control(self) -> str | None: ...
    @property
    def gains(self) -> str | None: ...
    @property
    def band(self) -> str | None: ...
    @property
    def seed(self) -> int | None: ...
    @property
    def no_noise(self) -> bool: ...
    @property
    def vibrations(self) -> Path | None: ...
    @property
    def no_vibrations(self) -> bool: ...
    @property
    def no_resonance(self) -> bool: ...
    @property
    def oversampling(self) -> int | None: ...
    @property
    def wfs_field(self) -> float | None: ...


def loop_overrides(o: LoopOptions) -> dict:
    """The options of a simulated loop as overrides of the run description's dotted fields
    (given options only; --gains through ``gain_overrides``)."""
    check_run_options(o.seeing, o.wind, o.L0, o.band, o.seed, oversampling=o.oversampling, wfs_field=o.wfs_field)
    if o.tt_control not in (None, *TT_CONTROLS):
        raise InputError(f"--tt-control must be 'iir' or 'int', got '{o.tt_control}'")
    values = {
        "atmosphere.seeing_arcsec": o.seeing,
        "atmosphere.wind_m_s": o.wind,
        "atmosphere.L0_m": o.L0,
        "control.tt_control": o.tt_control,
        "run.band": o.band,
        "run.seed": o.seed,
        "run.oversampling": o.oversampling,
        "run.wfs_field_arcsec": o.wfs_field,
        "detector.noise": False if o.no_noise else None,
        "vibrations.file": str(o.vibrations) if o.vibrations is not None and not o.no_vibrations else None,
        "vibrations.enabled": False if o.no_vibrations else None,
        "structure.enabled": False if o.no_resonance else None,
    }
    return {k: v for k, v in values.items() if v is not None} | gain_overrides(o.gains)


def probe_overrides(mode: int | None, amplitude: float | None, frequency: float | None) -> dict:
    """The --probe-* options as overrides of the run description's fields (given ones only)."""
    values = {"auxiliary.probe_mode": mode, "auxiliary.probe_amplitude_nm": amplitude, "auxiliary.probe_frequency_hz": frequency}
    return {k: v for k, v in values.items() if v is not None}


def run_description(config: Path | None, mag: str | None, overrides: dict) -> RunConfig:
    """The run of --config (a run description or a telemetry file) or --mag (the table's star;
    the default star without either), with the other options' overrides applied."""
    if config is not None and mag is not None:
        raise InputError("give either --config or --mag, not both")
    base = read_run_config(config) if config is not None else RunConfig()
    if mag is not None:
        overrides = {"star.magnitude_r": parse_magnitude(mag), **overrides}
    if quick.active():
        overrides = quick.run_overrides(overrides)
    description = base.with_values(overrides) if overrides else base
    return _quick(description) if quick.active() else description


def _quick(description: RunConfig) -> RunConfig:
    """A run description at SOULCTL_QUICK's cost (``cli.quick``): its duration capped, the
    auxiliary loops at their shortest update period unless one is given."""
    from ..loop.schedule import shortest_period_s  # only here: the optimiser's imports are heavy

    duration = quick.cap_duration(description.duration_s)
    values: dict = {"run.duration_s": duration}
    said = [f"the pyramid's field {description.wfs_field_arcsec:g}\""]
    if duration < description.duration_s:
        said.append(f"{duration:g} s of loop instead of {description.duration_s:g} s")
    aux = description.auxiliary
    if aux.period_s is None and (aux.mgm or aux.ogtl):
        values["auxiliary.period_s"] = shortest_period_s(description.observation, aux.probe())
        said.append(f"MGM/OGTL every {values['auxiliary.period_s']:g} s")
    quick.notice(", ".join(said))
    return description.with_values(values)


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
        if o.get("ncpa_offsets_at_frame") is not None:
            rows.append(("NCPA offsets applied (OGTL's k calibrated)", f"from frame {o['ncpa_offsets_at_frame']}"))
    if "mgm" in s:
        rows.append(("MGM updates (noise-dominated modes, last)", f"{s['mgm']['updates']} ({s['mgm']['noise_dominated_modes_last']})"))
    if "safety" in s:
        f = s["safety"]
        rows.append(
            ("safety net: restores of the last good gains and k", f"{f['restores']}" + (" (could not recover)" if f["gave_up"] else ""))
        )
    return rows


def misregistration_overrides(text: str | None) -> dict:
    """--misregistration DX,DY[,ROT[,MAG]] as the run description's [misregistration] fields."""
    if text is None:
        return {}
    cells = [c.strip() for c in text.split(",")]
    if not 2 <= len(cells) <= 4:
        raise InputError(f"--misregistration takes DX,DY[,ROT[,MAG]] (2 to 4 numbers), got {text!r}")
    values = {}
    for key, cell, accepted in zip(REGISTRATION_KEYS, cells, (SHIFT_PITCH, SHIFT_PITCH, ROTATION_DEG, MAGNIFICATION)):
        try:
            value = float(cell)
        except ValueError:
            raise InputError(f"--misregistration {key} must be a number in {accepted.text()}, got {cell!r}") from None
        values[f"misregistration.{key}"] = accepted.check(value, f"--misregistration {key}")
    return values
