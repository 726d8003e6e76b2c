"""``soulctl configure``: the observation set-up for a guide star, from the look-up table."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from .. import tables
from ..files import check_output_path
from ..observation import Observation, observation_for_magnitude
from .numbers import magnitude_option, parse_magnitude
from .output import JSON_OUTPUT, print_json
from .output import console as make_console


def render(obs: Observation, console: Console, roots_source: str = "roots") -> None:
    bands = tables.magnitude_table()
    band = tables.band_for_magnitude(obs.magnitude_r, bands)
    t = Table(
        title=f"SOUL configuration for an R = {obs.magnitude_r:g} guide star\n(look-up table row {band.label(first=band == bands[0])})",
        title_justify="left",
    )
    t.add_column("parameter")
    t.add_column("value", justify="right")
    t.add_column("source", style="dim")
    row = "look-up table"
    t.add_row("binning", f"{obs.binning}", row)
    t.add_row("sub-apertures across", f"{obs.subapertures} x {obs.subapertures}", row)
    t.add_row("controlled modes", f"{obs.modes}", row)
    rate_src = (
        "fixed by the row"
        if band.frame_rate_max_hz == band.frame_rate_min_hz
        else f"flux rule, {band.frame_rate_max_hz:g}..{band.frame_rate_min_hz:g} Hz"
    )
    t.add_row("frame rate", f"{obs.frame_rate_hz:g} Hz", rate_src)
    t.add_row("modulation radius", f"{obs.modulation_lambda_over_d:g} λ/D", row)
    if obs.tt_control == "iir":
        t.add_row("Tip/Tilt control", "IIR (N_f = 8)", f"{roots_source} at {obs.tt_filter_rate_hz:g} Hz")
        t.add_row("  zeros", " ".join(f"{z:+.3f}" for z in obs.tt_zeros), "")
        t.add_row("  poles", " ".join(f"{p:+.3f}" for p in obs.tt_poles), "")
        if obs.tt_gain is not None:
            t.add_row("  gain", f"{obs.tt_gain:g}", f"designed with the filter ({roots_source})")
    else:
        t.add_row("Tip/Tilt control", "integrator", f"rate below the {roots_source} table")
    t.add_row("other modes", "leaky integrators", "")
    t.add_row("loop delay", f"{obs.delay_s * 1e3:.2f} ms = {obs.delay_frames:.2f} frames", "delay model")
    t.add_row("photons/sub-ap./frame", f"{obs.photons_per_subaperture_per_frame:.1f}", "WFS zero point")
    console.print(t)


def configure(
    mag: str = magnitude_option(...),
    out: Path | None = typer.Option(
        None, "--out", metavar="FILE", help="Write the configuration as TOML (for --config of later commands)."
    ),
    roots: Path | None = typer.Option(
        None,
        "--roots",
        metavar="FILE",
        help="Tip/Tilt IIR roots table to use instead of the paper's (e.g. from 'soulctl filter design --out').",
    ),
    json_output: bool = JSON_OUTPUT,
) -> None:
    """Set up an observation for a guide star of R magnitude from the SOUL look-up table.

    The table gives the binning, sub-apertures, controlled modes, frame rate, modulation, Tip/Tilt filter, loop delay
    and expected photons per sub-aperture per frame.

    Example: soulctl configure --mag 13 --out obs.toml
    (--roots FILE takes the Tip/Tilt filter from a designed roots table.)
    """
    if out is not None:
        check_output_path(out, "--out", [("--roots", roots)])
    roots_table = tables.read_roots_table(roots) if roots is not None else None
    obs = observation_for_magnitude(parse_magnitude(mag), roots_table, roots_source=str(roots) if roots is not None else None)
    if out is not None:
        obs.write_toml(out)
    if json_output:
        print_json(obs.to_dict())
    else:
        console = make_console()
        render(obs, console, roots_source=f"{roots.name}" if roots is not None else "roots")
        if out is not None:
            console.print(f"written {out}")
