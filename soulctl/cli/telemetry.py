"""``soulctl telemetry inspect|psd|convert``: a loop's records in any format soulctl reads
(its HDF5, AOT FITS, an LBT tracking-number folder)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import typer

from ..errors import InputError
from ..files import atomic_write_text, check_output_folder, check_output_path
from ..identify.identify import Identification, identify
from ..plots.telemetry import IDENTIFY_FIGURES, write_identify_figures, write_psd_figure
from ..ranges import DELAY_FRAMES
from ..telemetry.analysis import inspect, spectra
from ..telemetry.figures import RECORD_LABELS as LABELS
from ..telemetry.figures import mas_text
from ..telemetry.formats import open_telemetry, read_record, telemetry_format, telemetry_input, write_record
from . import progress
from .common import CACHE_DIR, JSON_OUTPUT, NO_CACHE, RECORD_DELAY, RESONANCE, array_cache, check_resonance, quantity_table
from .numbers import number
from .option_table import command
from .output import console as make_console
from .output import figure_text, print_json, warn

app = typer.Typer(no_args_is_help=True, help="Loop telemetry: inspect, spectra, conversion between formats, plant identification.")

SOURCE = typer.Argument(..., metavar="FILE|DIR", help="Telemetry: soulctl HDF5 (.h5), AOT FITS (.fits) or an LBT tracking-number folder.")


@dataclass(frozen=True)
class InspectOptions:
    path: Path = SOURCE
    json_output: bool = JSON_OUTPUT


@app.command("inspect")
@command(InspectOptions)
def inspect_cmd(o: InspectOptions) -> int:
    """What a telemetry record holds and whether it is complete.

    Rate, frames, duration, decimation and gaps, fields with shapes and units, modes,
    status (complete or partial, and why) and the run description of a telemetry record.

    Example: soulctl telemetry inspect run.h5
    """
    telemetry_input(o.path)
    with open_telemetry(o.path, required=()) as tm:
        d = inspect(tm, telemetry_format(o.path))
    if o.json_output:
        print_json(d)
        return 0
    t = quantity_table(f"telemetry {o.path} ({d['format']})")
    rows = [
        ("status", d["status"] + (f": {d['partial_reason']}" if d["partial_reason"] else "")),
        ("frame rate [Hz]", _text(d["rate_hz"])),
        ("delay [frames]", _text(d["delay_frames"])),
        ("frames recorded", str(d["frames"])),
        ("duration [s]", _text(d["duration_s"])),
        ("decimation / gaps / lost frames", f"{d['decimation']} / {d['gaps']} / {d['lost_frames']}"),
        ("modes", _text(d["modes"])),
        ("auxiliary loops", ", ".join(d["auxiliary_loops"]) or "-"),
        ("run description", "yes" if d["run_description"] else "no"),
        ("sensor / corrector", f"{d['sensor'] or 'not stated'} / {d['corrector'] or 'not stated'}"),
        ("telescope", _telescope_text(d)),
    ]
    rows += [(name, f"{tuple(f['shape'])} {f['unit']}") for name, f in d["fields"].items()]
    rows += [(f"note ({n['field']})" if n["field"] else "note", n["note"]) for n in d["notes"]]
    for label, value in rows:
        t.add_row(label, value)
    make_console().print(t)
    return 0


def _telescope_text(d: dict) -> str:
    if d["telescope"] is None and d["telescope_diameter_m"] is None:
        return "not stated"
    size = f" ({d['telescope_diameter_m']:g} m)" if d["telescope_diameter_m"] is not None else ""
    return f"{d['telescope'] or 'unnamed'}{size}"


def _text(value) -> str:
    return "-" if value is None else figure_text(value)


def _modes(text: str) -> tuple[int, ...]:
    try:
        modes = tuple(int(m) for m in text.split(","))
    except ValueError:
        raise InputError(f"--modes must be mode numbers separated by commas (1-based), got '{text}'") from None
    if not modes or len(set(modes)) != len(modes):
        raise InputError(f"--modes must name each mode once, got '{text}'")
    return modes


@dataclass(frozen=True)
class PsdOptions:
    path: Path = SOURCE
    modes: str = typer.Option("1,2", "--modes", metavar="M1,M2", help="Modes (1-based); with 1 and 2, the cumulative Tip/Tilt jitter.")
    pseudo_open_loop: bool = typer.Option(False, "--pseudo-open-loop", help="Also the pseudo-open-loop modes (R s + delayed M^-1 c).")
    delay_frames: float | None = RECORD_DELAY
    plot: Path | None = typer.Option(None, "--plot", metavar="FILE.png", help="Write the PSDs and the cumulative jitter.")
    json_output: bool = JSON_OUTPUT


JITTER_ROWS = (("all", "all"), ("above_3hz", "above 3 Hz"))


@app.command("psd")
@command(PsdOptions)
def psd_cmd(o: PsdOptions) -> int:
    """Modal PSDs and the cumulative Tip/Tilt jitter of a telemetry record.

    Welch PSDs of measured (R s), command (M^-1 c) and pseudo-open-loop modes, and the
    cumulative Tip/Tilt jitter in mas from each frequency to Nyquist, as in the paper's figures:
    as measured, and with each record's white noise floor (the PSD's median over the top
    quarter of the band) removed.

    Example: soulctl telemetry psd run.h5 --modes 1,2,30 --pseudo-open-loop --plot psd.png
    """
    modes = _modes(o.modes)
    if o.delay_frames is not None:
        DELAY_FRAMES.check(o.delay_frames, "--delay-frames")
    telemetry_input(o.path)
    if o.plot is not None:
        check_output_path(o.plot, "--plot", [("FILE", o.path)])
    with open_telemetry(o.path, required=("rate_hz",)) as tm:
        s = spectra(tm, modes, o.pseudo_open_loop, o.delay_frames)
    for text in s.warnings:
        warn(text)
    if o.plot is not None:
        write_psd_figure(o.plot, s, str(o.path))
    jitter = s.tip_tilt_jitter()
    if o.json_output:
        print_json(
            {
                "f_hz": s.f_hz,
                "modes": list(s.modes),
                "window_frames": list(s.window),
                "psd_nm2_per_hz": {name: p for name, p in s.psd.items()},
                "noise_floor_nm2_per_hz": s.floor,
                "nm_per_mas": s.nm_per_mas,
                "tt_cumulative_f_hz": {name: j.f_hz for name, j in s.jitter.items()},
                "tt_cumulative_mas": {name: j.cumulative_mas for name, j in s.jitter.items()},
                "tt_jitter_mas": {name: j["all"] for name, j in jitter.items()},
                "tt_jitter_above_3hz_mas": {name: j["above_3hz"] for name, j in jitter.items()},
                "tt_jitter": jitter,
                "warnings": list(s.warnings),
                "notes": list(s.notes),
            }
        )
        return 0
    first, stop = s.window
    t = quantity_table(f"spectra of {o.path}: modes {o.modes}, frames {first}..{stop - 1}, resolution {s.f_hz[1]:.3g} Hz")
    for name, p in s.psd.items():
        rms = np.sqrt(np.sum(p, axis=1) * s.f_hz[1])
        t.add_row(f"{LABELS.get(name, name)} RMS [nm]", ", ".join(f"{v:.3g}" for v in rms))
    for name, j in jitter.items():
        values = " / ".join(mas_text(j[key]) for key, _ in JITTER_ROWS)
        t.add_row(f"{LABELS.get(name, name)} Tip/Tilt jitter per axis [mas]: all / above 3 Hz ({j['resolution_hz']:.3g} Hz bins)", values)
        t.add_row("  less the white noise floor", " / ".join(mas_text(j[f"{key}_floor_removed"]) for key, _ in JITTER_ROWS))
        t.add_row("  the white noise floor", " / ".join(mas_text(j[f"{key}_noise_floor"]) for key, _ in JITTER_ROWS))
    for note in s.notes:
        t.add_row("note", note)
    make_console().print(t)
    return 0


@dataclass(frozen=True)
class ConvertOptions:
    source: Path = SOURCE
    target: Path = typer.Argument(..., metavar="OUT", help="The format by the name: .h5, .fits, or a new folder (LBT TN layout).")


@app.command("convert")
@command(ConvertOptions)
def convert_cmd(o: ConvertOptions) -> int:
    """Convert telemetry between soulctl HDF5, AOT FITS and LBT tracking-number folders.

    Each field both formats hold is kept; docs/telemetry-formats.md has the mapping.

    Example: soulctl telemetry convert run.h5 run.fits
    """
    telemetry_input(o.source)
    if telemetry_format(o.target) != "lbt":
        check_output_path(o.target, "OUT", [("FILE", o.source)])
    arrays, attributes = read_record(o.source)
    write_record(o.target, arrays, attributes)
    return 0


@dataclass(frozen=True)
class IdentifyOptions:
    path: Path = SOURCE
    out: Path | None = typer.Option(
        None,
        "--out",
        metavar="PLANT.toml",
        help="Write the plant file (filter design|analyze --plant, loop run --plant, rtc check --plant).",
    )
    vibrations_out: Path | None = typer.Option(
        None, "--vibrations-out", metavar="FILE.toml", help="Write the vibration lines alone, as a --vibrations file."
    )
    delay_frames: float | None = typer.Option(
        None,
        "--delay-frames",
        parser=number(DELAY_FRAMES),
        metavar="D",
        help="Centre of the delay search (default: the record's, else the configuration's).",
    )
    plot: Path | None = typer.Option(None, "--plot", metavar="DIR", help="Write " + ", ".join(IDENTIFY_FIGURES) + ".")
    resonance: str = RESONANCE
    no_cache: bool = NO_CACHE
    cache_dir: Path | None = CACHE_DIR
    json_output: bool = JSON_OUTPUT


@app.command("identify")
@command(IdentifyOptions)
def identify_cmd(o: IdentifyOptions) -> int:
    """Identify the plant from closed-loop telemetry.

    The plant is the loop delay, optical gains, measurement
    noise per mode, Tip/Tilt vibration lines and seeing/L0, each with its uncertainty
    (docs/physics.md, "Identification").

    Example: soulctl telemetry identify run.h5 --out plant.toml --plot figs
    """
    if o.delay_frames is not None:
        DELAY_FRAMES.check(o.delay_frames, "--delay-frames")
    check_resonance(o.resonance)
    telemetry_input(o.path)
    for path, option in ((o.out, "--out"), (o.vibrations_out, "--vibrations-out")):
        if path is not None:
            check_output_path(path, option, [("FILE", o.path)])
    if o.plot is not None:
        check_output_folder(o.plot, "--plot", IDENTIFY_FIGURES)
    with progress.step(f"identifying the plant of {o.path}"):
        ident = identify(o.path, o.delay_frames, array_cache(o.no_cache, o.cache_dir), o.resonance)
    if o.out is not None:
        atomic_write_text(o.out, ident.plant.to_toml())
    if o.vibrations_out is not None:
        if ident.plant.vibrations is None:
            raise InputError(f"--vibrations-out: no vibration line found in {o.path}: nothing to write")
        atomic_write_text(o.vibrations_out, ident.plant.vibrations_toml())
    if o.plot is not None:
        write_identify_figures(o.plot, ident)
    if o.json_output:
        print_json(ident.to_dict())
        return 0
    make_console().print(_identify_table(ident))
    return 0


L0_LABEL = "outer scale L0 [m]"


def _identify_table(ident: Identification):
    p = ident.plant
    t = quantity_table(f"plant identified from {ident.record.path} ({ident.record.frames / p.rate_hz:.3g} s window)")
    recorded = ident.record.delay_frames
    t.add_row("loop delay [frames]", f"{p.delay.value:.3f} ± {p.delay.sigma:.3f} ({_recorded(recorded)})")
    if ident.probe is not None:
        pr = ident.probe
        t.add_row(
            f"probe, mode {pr.mode} at {pr.frequency_hz:g} Hz",
            f"chi {pr.chi.value:.3f} ± {pr.chi.sigma:.3f}, d {pr.delay.value:.3f} ± {pr.delay.sigma:.3f}",
        )
    for g in p.optical_gains:
        modes = f"mode {g.first_mode}" if g.first_mode == g.last_mode else f"modes {g.first_mode}-{g.last_mode}"
        t.add_row(f"optical gain chi, {modes}", f"{g.chi:.3f} ± {g.sigma:.3f}")
    if p.tip_tilt_noise_mas is not None:
        t.add_row("Tip/Tilt noise [mas RMS per frame]", f"{p.tip_tilt_noise_mas:.3g}")
    if p.turbulence is not None:
        tu = p.turbulence
        t.add_row("seeing at 500 nm [arcsec]", f"{tu.seeing_arcsec:.3f} ± {tu.seeing_sigma:.3f}")
        if "L0" not in ident.not_estimated:
            t.add_row(L0_LABEL, f"{figure_text(tu.L0_m)} ± {figure_text(tu.L0_sigma)}")
    for x in ident.lines:
        t.add_row(
            f"vibration {x.frequency.value:.2f} ± {x.frequency.sigma:.2f} Hz",
            f"tip {x.tip.value:.2f}, tilt {x.tilt.value:.2f} mas, damping {x.damping:.2g}",
        )
    if ident.line_limit is not None:
        lim = ident.line_limit
        found = "none found; " if not ident.lines else ""
        t.add_row(
            "vibration lines: detection limit",
            f"{found}{lim['rms_mas']:.2f} mas RMS per axis at {lim['at_hz']:g} Hz "
            f"(a line narrower than the {lim['resolution_hz']:.3g} Hz bins)",
        )
    for figure, why in ident.not_estimated.items():
        t.add_row(L0_LABEL if figure == "L0" else figure.replace("_", " "), f"not estimated: {why}")
    for note in p.notes:
        t.add_row("note", note)
    return t


def _recorded(delay: float) -> str:
    return f"recorded {figure_text(delay)}" if math.isfinite(delay) else "the record states none: searched 0-6 frames"
