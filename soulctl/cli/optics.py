"""``soulctl optics``: the optical models on their own: turbulence figures, calibration
(interaction matrix, cached) and the modal optical-gain table MGM needs."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import typer
from rich.table import Table

from .. import defaults, tables
from ..disturbance.turbulence import TurbulenceTipTilt
from ..errors import InputError
from ..files import check_output_path
from ..observation import BINNINGS
from ..optics.asm import AsmGeometry
from ..optics.atmosphere import AtmosphereConfig, r0_at_wavelength
from ..optics.cache import ArrayCache
from ..optics.calibration import BasisSetup, CalibrationSetup, calibrate
from ..optics.optical_gains import CHI_TABLE_SEEING_ARCSEC, CorrectionLevel, OpticalGainTable, optical_gains
from ..optics.optical_gains import SCREENS as GAIN_SCREENS
from ..optics.pwfs import PyramidConfig
from ..ranges import (
    BINNING,
    FRACTION,
    MODES,
    MODULATION_LAMBDA_OVER_D,
    OVERSAMPLING,
    SCREENS,
    SEED,
    SEEING_ARCSEC,
    WFS_FIELD_OF_VIEW_ARCSEC,
)
from ..run_config import RunConfig, read_run_config
from . import progress, quick
from .common import (
    CACHE_DIR,
    NO_CACHE,
    RUN_CONFIG,
    WFS_FIELD,
    array_cache,
    observation_option,
    outer_scale_option,
    quantity_table,
    seeing_option,
    wind_option,
)
from .numbers import magnitude_option, number
from .option_table import command
from .output import JSON_OUTPUT, print_json
from .output import console as make_console

app = typer.Typer(no_args_is_help=True, help="Optical models: turbulence, calibration, optical gains.")


def table_modes(binning: int) -> int:
    """Controlled modes of the look-up table's rows at this binning (500/250/90/54)."""
    return next(band.modes for band in tables.magnitude_table() if band.binning == binning)


def sensing_setup(
    config: Path | None,
    mag: str | None,
    binning: int | None,
    modes: int | None,
    modulation: float | None,
    oversampling: int | None,
    wfs_field: float | None = None,
) -> CalibrationSetup:
    """The calibration set-up: with --config the pyramid and mirror its run holds (observation,
    oversampling, field of view, influence functions: ``loop.run.calibration_setup``), with
    --mag the table's row and the runs' defaults, without either binning 1 and the table's modes
    for it; explicit --binning/--modes/--modulation/--oversampling/--wfs-field override."""
    if config is not None and mag is not None:
        raise InputError("give either --config or --mag, not both")
    if quick.active() and wfs_field is None:
        wfs_field = quick.FIELD_ARCSEC
        quick.notice(f"the pyramid's field {wfs_field:g}\"")
    run = read_run_config(config) if config is not None else RunConfig()  # the runs' defaults
    obs = run.observation if config is not None else observation_option(None, mag)
    b = binning if binning is not None else (obs.binning if obs else 1)
    if b not in BINNINGS:
        raise InputError(f"--binning must be one of 1, 2, 3, 4, got {b}")
    n = modes if modes is not None else (obs.modes if obs and binning is None else table_modes(b))
    r = modulation if modulation is not None else (obs.modulation_lambda_over_d if obs else 3.0)
    o = oversampling if oversampling is not None else run.oversampling
    field = wfs_field if wfs_field is not None else run.wfs_field_arcsec
    for value, accepted, option in (
        (r, MODULATION_LAMBDA_OVER_D, "--modulation"),
        (n, MODES, "--modes"),
        (o, OVERSAMPLING, "--oversampling"),
        (field, WFS_FIELD_OF_VIEW_ARCSEC, "--wfs-field"),
    ):
        accepted.check(value, option)
    pyramid = PyramidConfig(binning=b, modulation_lambda_over_d=r, oversampling=o, field_of_view_arcsec=field)
    return CalibrationSetup(pyramid, n, BasisSetup(AsmGeometry(influence=run.influence)))


_MAG = magnitude_option()
_BINNING = typer.Option(None, "--binning", parser=number(BINNING), help="Detector binning 1..4 (40/20/13/10 sub-apertures across).")
_MODES = typer.Option(
    None, "--modes", parser=number(MODES), help=f"Controlled modes ({MODES.text()}; default: the look-up table's for the binning)."
)
_MODULATION = typer.Option(
    None,
    "--modulation",
    metavar="LAMBDA/D",
    parser=number(MODULATION_LAMBDA_OVER_D),
    help=f"Modulation radius in lambda/D ({MODULATION_LAMBDA_OVER_D.text()}; default 3).",
)
_OVERSAMPLING = typer.Option(
    None,
    "--oversampling",
    parser=number(OVERSAMPLING),
    help=f"Simulation pixels per binning-1 detector pixel (1..4; default: --config's, else {defaults.OVERSAMPLING}).",
)
_JSON = JSON_OUTPUT


@app.command("atmosphere")
def atmosphere(
    seeing: float = seeing_option(defaults.SEEING_ARCSEC),
    wind: float = wind_option(defaults.WIND_M_S),
    L0: float = outer_scale_option(defaults.L0_M),
    json_output: bool = _JSON,
) -> None:
    """Turbulence figures of the default LBT profile.

    They are r0 at 500 nm, the WFS and science bands,
    tau0, the layers, and the one-axis Tip/Tilt (von Karman) on the 8.222 m pupil.

    Example: soulctl optics atmosphere --seeing 0.8 --wind 10
    """
    atm = AtmosphereConfig.lbt_default(seeing_arcsec=seeing, L0_m=L0, wind_speed_m_s=wind)
    r0 = atm.r0_m
    tilt = TurbulenceTipTilt(seeing_arcsec=seeing, outer_scale_m=L0, wind_speed_m_s=atm.effective_wind_speed_m_s)
    tilt_mas = math.sqrt(tilt.variance_mas2())
    result: dict[str, Any] = {
        "seeing_arcsec": seeing,
        "L0_m": L0,
        "r0_500nm_m": r0,
        "r0_750nm_m": r0_at_wavelength(r0, 750e-9),
        "r0_1650nm_m": r0_at_wavelength(r0, 1.65e-6),
        "effective_wind_m_s": atm.effective_wind_speed_m_s,
        "tau0_500nm_ms": 0.314 * r0 / atm.effective_wind_speed_m_s * 1e3,
        "tilt_rms_per_axis_mas": tilt_mas,
        "layers": [
            {"altitude_m": layer.altitude_m, "weight": w, "wind_m_s": layer.wind_speed_m_s, "direction_deg": layer.wind_direction_deg}
            for layer, w in zip(atm.layers, atm.weights)
        ],
    }
    if json_output:
        print_json(result)
    else:
        _render_atmosphere(result)


def _render_atmosphere(result: dict[str, Any]) -> None:
    """The turbulence figures as a table."""
    r0, seeing, L0 = result["r0_500nm_m"], result["seeing_arcsec"], result["L0_m"]
    t = quantity_table(f'Turbulence: seeing {seeing:g}" at 500 nm, L0 {L0:g} m, LBT profile')
    t.add_row("r0 at 500 / 750 / 1650 nm", f"{r0 * 100:.1f} / {result['r0_750nm_m'] * 100:.1f} / {result['r0_1650nm_m'] * 100:.1f} cm")
    t.add_row("effective wind", f"{result['effective_wind_m_s']:.1f} m/s")
    t.add_row("tau0 at 500 nm", f"{result['tau0_500nm_ms']:.2f} ms")
    t.add_row("Tip/Tilt per axis (von Kármán)", f"{result['tilt_rms_per_axis_mas']:.0f} mas RMS")
    for i, layer in enumerate(result["layers"], 1):
        t.add_row(
            f"layer {i}",
            f"{layer['altitude_m']:g} m, {layer['weight'] * 100:.0f}% Cn², {layer['wind_m_s']:.1f} m/s at {layer['direction_deg']:g}°",
        )
    make_console().print(t)


def _calibration_dict(cal, cache: ArrayCache) -> dict:
    c = cal.setup.pyramid
    n_slopes = cal.interaction_matrix.shape[0]
    return {
        "binning": c.binning,
        "subapertures_across": BINNINGS[c.binning],
        "valid_subapertures": n_slopes // 2,
        "slopes": n_slopes,
        "modes": cal.setup.n_modes,
        "modulation_lambda_over_d": c.modulation_lambda_over_d,
        "modulation_points": c.points,
        "wfs_wavelength_nm": c.wavelength_m * 1e9,
        "pupil_pixels": c.pupil.n_pixels,
        "oversampling": c.oversampling,
        "wfs_field_arcsec": c.field_of_view_arcsec,
        "influence": cal.setup.basis.asm.influence,
        "field_stop_lambda_over_d": c.stop_lambda_over_d,
        "sensing_pupil_pixels": c.sensing_pupil.n_pixels,
        "fft_size": c.fft_size,
        "frame_shape": list(c.frame_shape),
        "push_nm": cal.setup.push_nm,
        "condition_number": cal.condition_number,
        "from_cache": cal.from_cache,
        "cache_file": str(cache.path(cal.setup.key())) if cache.directory else None,
        "seconds": cal.seconds,
    }


@app.command("calibrate")
def calibrate_cmd(
    config: Path | None = RUN_CONFIG,
    mag: str | None = _MAG,
    binning: int | None = _BINNING,
    modes: int | None = _MODES,
    modulation: float | None = _MODULATION,
    oversampling: int | None = _OVERSAMPLING,
    wfs_field: float | None = WFS_FIELD,
    no_cache: bool = NO_CACHE,
    cache_dir: Path | None = CACHE_DIR,
    json_output: bool = _JSON,
) -> None:
    """Calibrate the PWFS on the ASM's modes.

    It measures a push-pull interaction matrix around the unaberrated reference, and gives
    the pseudo-inverse reconstructor and the reference slopes.  The result is
    cached under a key of the configuration, so later runs reuse it (--no-cache recomputes).

    Example: soulctl optics calibrate --mag 13
    """
    setup = sensing_setup(config, mag, binning, modes, modulation, oversampling, wfs_field)
    cache = array_cache(no_cache, cache_dir)
    with progress.step(f"calibrating the pyramid on {setup.n_modes} modes (the first time; cached after)"):
        cal = calibrate(setup, cache)
    d = _calibration_dict(cal, cache)
    if json_output:
        print_json(d)
        return
    t = quantity_table("PWFS calibration")
    t.add_row("binning / sub-apertures across", f"{d['binning']} / {d['subapertures_across']}")
    t.add_row("valid sub-apertures / slopes", f"{d['valid_subapertures']} / {d['slopes']}")
    t.add_row("controlled modes", f"{d['modes']}")
    t.add_row("modulation", f"{d['modulation_lambda_over_d']:g} λ/D, {d['modulation_points']} points")
    t.add_row("pupil / sensing pupil / FFT", f"{d['pupil_pixels']} / {d['sensing_pupil_pixels']} / {d['fft_size']} px")
    t.add_row("detector frame", f"{d['frame_shape'][0]}x{d['frame_shape'][1]} px")
    field = (
        f'{d["wfs_field_arcsec"]:g}" (stop radius {d["field_stop_lambda_over_d"]:.1f} λ/D)' if d["wfs_field_arcsec"] else "sampled, no stop"
    )
    t.add_row("field of view", field)
    t.add_row("interaction matrix condition number", f"{d['condition_number']:.1f}")
    t.add_row("source", ("cache" if d["from_cache"] else "computed") + f" in {d['seconds']:.1f} s")
    if d["cache_file"]:
        t.add_row("cache file", d["cache_file"])
    make_console().print(t)


@dataclass(frozen=True)
class OpticalGainsOptions:
    """The options of `optics gains` (an option table: see ``option_table``)."""

    seeing: float = typer.Option(
        CHI_TABLE_SEEING_ARCSEC,
        "--seeing",
        metavar="ARCSEC",
        parser=number(SEEING_ARCSEC),
        help=f"Seeing of the correction level (the paper's table: {CHI_TABLE_SEEING_ARCSEC:g}; {SEEING_ARCSEC.text()}).",
    )
    L0: float = outer_scale_option(defaults.L0_M)
    controlled_fraction: float = typer.Option(
        CorrectionLevel.controlled_fraction,
        "--controlled-fraction",
        parser=number(FRACTION),
        help="Amplitude of the controlled modes left in the residual (0..1).",
    )
    config: Path | None = RUN_CONFIG
    mag: str | None = _MAG
    binning: int | None = _BINNING
    modes: int | None = _MODES
    modulation: float | None = _MODULATION
    oversampling: int | None = _OVERSAMPLING
    wfs_field: float | None = WFS_FIELD
    screens: int = typer.Option(
        GAIN_SCREENS,
        "--screens",
        parser=number(SCREENS),
        help=f"Residual phase realisations to average ({SCREENS.text()}; ~10 s each at 40x40).",
    )
    seed: int = typer.Option(defaults.SEED, "--seed", parser=number(SEED), help=f"Seed of the residual phase screens ({SEED.text()}).")
    out: Path | None = typer.Option(None, "--out", metavar="FILE.csv", help="Write the table (mode, optical_gain, spread) as CSV.")
    no_cache: bool = NO_CACHE
    cache_dir: Path | None = CACHE_DIR
    json_output: bool = _JSON


@app.command("gains")
@command(OpticalGainsOptions)
def gains_cmd(o: OpticalGainsOptions) -> int:
    """Modal optical gains of the PWFS at a correction level.

    Each mode's sensitivity around
    residual phases (turbulence of --seeing minus the corrected part of the controlled modes)
    relative to its diffraction-limited sensitivity.  MGM reads this table (chi_i).

    Example: soulctl optics gains --seeing 0.8 --mag 9.7 --out og_R9.7.csv
    """
    level = CorrectionLevel(seeing_arcsec=o.seeing, L0_m=o.L0, controlled_fraction=o.controlled_fraction)
    SCREENS.check(o.screens, "--screens")
    SEED.check(o.seed, "--seed")
    if o.out is not None:
        check_output_path(o.out, "--out", [("--config", o.config)])
    setup = sensing_setup(o.config, o.mag, o.binning, o.modes, o.modulation, o.oversampling, o.wfs_field)
    cache = array_cache(o.no_cache, o.cache_dir)
    screens = min(o.screens, quick.SCREENS) if quick.active() else o.screens
    if screens < o.screens:
        quick.notice(f"{screens} residual screen instead of {o.screens}")
    status = f"optical gains of {setup.n_modes} modes on {screens} residual screens (~10 s each at 40x40)"
    with progress.step(status):
        cal = calibrate(setup, cache)
        table = optical_gains(cal, level, n_screens=screens, seed=o.seed)
    if o.out is not None:
        table.write_csv(o.out)
    if o.json_output:
        print_json(table.to_dict())
        return 0
    _render_gains(table, setup, o.seeing)
    if o.out is not None:
        make_console(stderr=True).print(f"wrote {o.out}")
    return 0


def _render_gains(table: OpticalGainTable, setup: CalibrationSetup, seeing: float) -> None:
    """The optical gains by mode range: mean and extremes."""
    g = table.gains
    t = Table(
        title=f'Optical gains at seeing {seeing:g}" (residual {table.residual_nm:.0f} nm RMS), '
        f"binning {setup.pyramid.binning}, modulation {setup.pyramid.modulation_lambda_over_d:g} λ/D, "
        + (f'field {table.wfs_field_arcsec:g}"' if table.wfs_field_arcsec else "sampled field"),
        title_justify="left",
    )
    t.add_column("modes")
    t.add_column("mean optical gain", justify="right")
    t.add_column("min..max", justify="right")
    edges = [0, 2, 10, 30, 120, 250, len(g)]
    for a, b in zip(edges[:-1], edges[1:]):
        if a >= len(g):
            break
        b = min(b, len(g))
        t.add_row(f"{a + 1}..{b}", f"{g[a:b].mean():.3f}", f"{g[a:b].min():.3f}..{g[a:b].max():.3f}")
    make_console().print(t)
