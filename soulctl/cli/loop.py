"""``soulctl loop run``: a simulated SOUL closed loop, from a guide star to Strehl and jitter."""

from __future__ import annotations

import signal
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.console import Console

from .. import defaults
from ..control.gains import MID_GROUP_END, gain_groups
from ..errors import InputError
from ..files import check_output_folder, check_output_path
from ..loop.metrics import BANDS
from ..ranges import DURATION_S, NCPA_OFFSET_FRACTION, NCPA_RMS_NM, TELEMETRY_EVERY
from ..telemetry.figures import mas_text
from ..telemetry.schema import DEFAULT_FIELDS, PER_FRAME
from . import common, progress
from .common import (
    BAND,
    CACHE_DIR,
    JSON_OUTPUT,
    NO_CACHE,
    NO_NOISE,
    NO_RESONANCE,
    NO_VIBRATIONS,
    OUTER_SCALE,
    PERIOD,
    PROBE_AMPLITUDE,
    PROBE_FREQUENCY,
    PROBE_MODE,
    RUN_CONFIG,
    SEED,
    SEEING,
    TT_CONTROL,
    VIBRATIONS,
    WIND,
    array_cache,
    aux_rows,
    aux_summary,
    check_run_options,
    gain_file_input,
    loop_overrides,
    probe_overrides,
    quantity_table,
    run_description,
)
from .numbers import magnitude_option, number
from .option_table import command

if TYPE_CHECKING:
    from ..telemetry.stream import Hdf5Writer

# The loop, its plots, its telemetry writer and the plant reader are imported where a run uses
# them, not at the top: `soulctl loop run --help` and a refused option pay for none of them.
from .output import console as make_console
from .output import figure_text, print_json, styled

app = typer.Typer(no_args_is_help=True, help="The simulated closed loop.")


def _result_dict(result) -> dict:
    m = result.metrics
    d = {
        "configuration": result.configuration(),
        "calibration": {
            "valid_subapertures": result.calibration.interaction_matrix.shape[0] // 2,
            "modes": result.calibration.basis.n_modes,
            "from_cache": result.calibration.from_cache,
            "seconds": result.calibration_seconds,
        },
        "seconds": result.seconds,
        "frames_per_second": len(result.telemetry.residual_rms_nm) / result.seconds if result.seconds > 0 else None,
        "diverged_at_frame": result.diverged_at,
        "metrics": None if m is None else m.to_dict(),
        "notes": list(result.notes),
    }
    if result.coupling is not None:
        d["misregistration_stability"] = result.coupling.to_dict()
    if result.telemetry.aux:
        d["auxiliary_loops"] = sorted(result.telemetry.aux)
        d["final_gains"] = result.final_gains.tolist()
        d["final_sensitivity"] = result.final_sensitivity
        d["auxiliary_summary"] = aux_summary({name: result.telemetry.aux_arrays(name) for name in result.telemetry.aux})
    return d


def _value(m, name: str, spec: str, unit: str = "") -> str:
    """Metric ``name`` as the table shows it; 'n/a (why)' when it is not available."""
    x = getattr(m, name)
    if x is None:
        return f"n/a ({m.not_available.get(name, 'run too short')})"
    return (mas_text(x) if spec == "mas" else format(x, spec)) + unit


def _render(result, console: Console) -> None:
    r, m = result.request, result.metrics
    obs = r.observation
    t = quantity_table(
        f"Closed loop: R = {obs.magnitude_r:g}, {obs.subapertures}x{obs.subapertures}, {obs.modes} modes, "
        f'{obs.frame_rate_hz:g} Hz, seeing {figure_text(r.seeing_arcsec)}", {r.duration_s:g} s'
    )
    g = result.gains
    t.add_row("Tip/Tilt control", f"{'IIR' if obs.tt_control == 'iir' else 'integrator'}, gain {g.tip_tilt:.3g}")
    if obs.modes > MID_GROUP_END:
        t.add_row(
            f"gains modes 3-{MID_GROUP_END} / {MID_GROUP_END + 1}-last", f"{g.mid:.3g} / {g.high:.3g}" + (" (gain file)" if g.modes else "")
        )
    else:
        t.add_row(f"gains modes 3-{obs.modes}", f"{g.mid:.3g}" + (" (gain file)" if g.modes else ""))
    t.add_row(f"Strehl ratio ({r.band}, {BANDS[r.band] * 1e6:.4g} µm)", _value(m, "strehl", ".3f"))
    bins = "" if m.jitter_resolution_hz is None else f", {m.jitter_resolution_hz:.3g} Hz bins"
    t.add_row(f"Tip/Tilt jitter per axis, residual (true wavefront{bins})", _value(m, "tt_jitter_mas", "mas", " mas"))
    t.add_row(
        "Tip/Tilt jitter per axis, pseudo-open loop (all / > 3 Hz)",
        f"{_value(m, 'tt_jitter_pol_mas', 'mas', ' mas')} / {_value(m, 'tt_jitter_pol_3hz_mas', 'mas', ' mas')}",
    )
    t.add_row("residual wavefront error", _value(m, "residual_nm", ".0f", " nm RMS"))
    t.add_row("rejection at 13 Hz (telemetry)", _value(m, "rejection_13hz", ".3f"))
    t.add_row("frames (metrics on)", f"{m.frames} ({m.frames - m.skipped_frames})")
    if result.telemetry.aux:
        fg = result.final_gains
        t.add_row("auxiliary loops", ", ".join(sorted(result.telemetry.aux)))
        t.add_row("final gains Tip / Tilt", f"{fg[0]:.3f} / {fg[1]:.3f}")
        for name, modes in gain_groups(len(fg))[1:]:
            t.add_row(f"final gains {name} (mean)", f"{fg[modes].mean():.3f}")
        t.add_row("final slope sensitivity k", f"{result.final_sensitivity:.3f}")
        for label, text in aux_rows(result.telemetry):
            t.add_row(label, text)
    if result.coupling is not None:
        t.add_row("mis-registration: unstable eigenmodes", result.coupling.figures_text())
    t.add_row("simulation speed", f"{m.frames / result.seconds:.0f} frames/s" if result.seconds > 0 else "n/a")
    console.print(t)
    for note in result.notes:
        console.print(styled(f"note: {note}", "dim"))


@dataclass(frozen=True)
class RunOptions:
    """The options of `loop run` (an option table: see ``option_table``)."""

    config: Path | None = RUN_CONFIG
    mag: str | None = magnitude_option(None, f"{defaults.MAGNITUDE_R:g}, the paper's bright star")
    plant: Path | None = typer.Option(
        None,
        "--plant",
        metavar="PLANT.toml",
        help="A simulated twin of an identified plant ('telemetry identify --out'): its frame rate, delay, seeing, L0 "
        "and vibration lines (the other options override them).",
    )
    seeing: float | None = SEEING
    wind: float | None = WIND
    L0: float | None = OUTER_SCALE
    duration: float | None = typer.Option(
        None,
        "--duration",
        parser=number(DURATION_S),
        metavar="S",
        show_default=str(defaults.DURATION_S),
        help="Simulated time (s); the first 20 % is left out of the metrics.",
    )
    tt_control: str | None = TT_CONTROL
    gains: str | None = typer.Option(
        None, "--gains", metavar="TT,MID,HIGH|FILE", help="Gains of modes 1-2, 3-120, 121-last, or a per-mode gain file."
    )
    band: str | None = BAND
    seed: int | None = SEED
    no_noise: bool = NO_NOISE
    vibrations: Path | None = VIBRATIONS
    no_vibrations: bool = NO_VIBRATIONS
    no_resonance: bool = NO_RESONANCE
    oversampling: int | None = common.OVERSAMPLING
    wfs_field: float | None = common.WFS_FIELD
    misregistration: str | None = common.MISREGISTRATION
    ncpa: float | None = typer.Option(
        None,
        "--ncpa",
        parser=number(NCPA_RMS_NM),
        metavar="NM",
        show_default=f"{defaults.NCPA_RMS_NM:g} nm, LUCI1's in the paper's Sec. 3.1",
        help="Non-common-path aberration: NM RMS that the science camera sees and the pyramid does not.",
    )
    ncpa_offsets: bool | None = typer.Option(
        None,
        "--ncpa-offsets/--no-ncpa-offsets",
        show_default="with OGTL, once it has calibrated k",
        help="Compensate the NCPA's controlled part with reference-slope offsets (scaled by k as LBT does).",
    )
    ncpa_offset_fraction: float | None = typer.Option(
        None,
        "--ncpa-offset-fraction",
        parser=number(NCPA_OFFSET_FRACTION),
        metavar="F",
        show_default=f"{defaults.NCPA_OFFSET_FRACTION:g}: in full they tipped the pyramid into a false lock",
        help="Fraction of the NCPA offsets applied (0..1); the science path keeps 1 - F of the controlled part.",
    )
    allow_unstable: bool = typer.Option(False, "--allow-unstable", help="Run gains the analysis calls unstable.")
    mgm: bool = typer.Option(False, "--mgm", help="Run the Modal Gain Machine beside the loop (from the initial gains, every --period).")
    ogtl: bool | None = typer.Option(
        None,
        "--ogtl/--no-ogtl",
        show_default="on when the run is long enough for two updates",
        help="Run the optical gain tracking loop beside the loop (probe on --probe-mode), as SOUL does on sky.",
    )
    ideal: bool = typer.Option(False, "--ideal", help="The idealised loop: no OGTL, no NCPA, no mis-registration, a noiseless calibration.")
    period: float | None = PERIOD
    probe_mode: int | None = PROBE_MODE
    probe_amplitude: float | None = PROBE_AMPLITUDE
    probe_frequency: float | None = PROBE_FREQUENCY
    telemetry: Path | None = typer.Option(
        None,
        "--telemetry",
        metavar="FILE",
        help="Stream the telemetry to disk as the loop runs: FILE.h5 (HDF5), FILE.fits (AOT FITS) or a new Data_<TN> folder (LBT).",
    )
    telemetry_fields: str | None = typer.Option(
        None,
        "--telemetry-fields",
        metavar="F1,F2|all",
        help=f"Per-frame fields to record (default {','.join(DEFAULT_FIELDS)}; 'all' adds slopes and commands).",
    )
    telemetry_every: int = typer.Option(
        1, "--telemetry-every", parser=number(TELEMETRY_EVERY), metavar="N", help="Record one frame in N (frame_counter says which)."
    )
    plot: Path | None = typer.Option(None, "--plot", metavar="DIR", help="Write psf.png, jitter.png, modal_variance.png.")
    print_config: bool = typer.Option(
        False, "--print-config", help="Print the resolved run description (TOML; JSON with --json) and exit without running."
    )
    no_cache: bool = NO_CACHE
    cache_dir: Path | None = CACHE_DIR
    json_output: bool = JSON_OUTPUT


@app.command("run")
@command(RunOptions)
def run_cmd(o: RunOptions) -> int:
    """Close a simulated SOUL loop and print its Strehl ratio, jitter and residual.

    The loop has LBT turbulence and vibrations, the adaptive secondary with
    its 127 Hz structural resonance, the modulated pyramid with detector noise, the C++ slopes
    and RTC, the loop delay.  Prints the Strehl ratio, Tip/Tilt jitter (residual and
    pseudo-open loop), residual wavefront error and the 13 Hz rejection.  --mgm and --ogtl run
    the Modal Gain Machine and the optical gain tracking loop beside it once the loop has
    closed (their records go to the telemetry file).  The run is a run description (--config,
    else the defaults; --print-config shows it); every other option overrides one of its
    fields, and the telemetry file stores it, so that `--config t.h5` runs the same loop again.
    Exit status 3 if the loop diverges (the telemetry so far is still written), or if a
    --misregistration leaves eigenmodes of the loop unstable (the loop is lost: it runs to the
    end, its figures are still printed and its telemetry written).

    Example: soulctl loop run --mag 9.7 --seeing 1.0 --duration 1 --plot out/
    """
    overrides = _checked_overrides(o)
    description = run_description(o.config, o.mag, overrides).resolved()
    if o.print_config:
        print_json(description.to_dict()) if o.json_output else print(description.to_toml(), end="")
        return 0
    request = description.request()
    aux = description.auxiliary.live()
    if aux is not None:
        aux.check(request.observation, request.duration_s)
    cache = array_cache(o.no_cache, o.cache_dir)
    fields = telemetry_fields(o.telemetry_fields)
    from ..plots.loop import write_loop_figures
    from ..telemetry.stream import Hdf5Writer

    writer = None if o.telemetry is None else Hdf5Writer(o.telemetry, fields, o.telemetry_every, {"run_description": description.to_toml()})
    result = _run_streaming(request, cache, aux, writer)
    message = result.failure()
    if message is not None:
        if o.json_output:
            print_json(_result_dict(result))
        elif result.metrics is not None:  # a loop that ran to the end (lost, or beyond its safety net): its figures
            _render(result, make_console())
        print(f"soulctl: {message}" + (f"; telemetry written to {o.telemetry}" if o.telemetry else ""), file=sys.stderr)
        return 3
    if o.plot is not None:
        write_loop_figures(o.plot, result)
    if o.json_output:
        print_json(_result_dict(result))
    else:
        console = make_console()
        _render(result, console)
        if o.telemetry is not None:
            console.print(f"telemetry written to {o.telemetry}")
        if o.plot is not None:
            console.print(f"figures written to {o.plot}/")
    return 0


def _checked_overrides(o: RunOptions) -> dict:
    """Every option checked and the outputs checked before any work; the run description's
    overrides (the loop's options and `loop run`'s own)."""
    inputs = [("--config", o.config), gain_file_input(o.gains), ("--vibrations", o.vibrations), ("--plant", o.plant)]
    if o.telemetry is not None:
        check_output_path(o.telemetry, "--telemetry", inputs)
    if o.plot is not None:
        from ..plots.loop import LOOP_FIGURES

        check_output_folder(o.plot, "--plot", LOOP_FIGURES)
    check_run_options(None, None, None, None, None, o.duration)
    TELEMETRY_EVERY.check(o.telemetry_every, "--telemetry-every")
    if o.ncpa is not None:
        NCPA_RMS_NM.check(o.ncpa, "--ncpa")
    if o.ncpa_offset_fraction is not None:
        NCPA_OFFSET_FRACTION.check(o.ncpa_offset_fraction, "--ncpa-offset-fraction")
    telemetry_fields(o.telemetry_fields)
    overrides = loop_overrides(o)
    from ..identify.plant import plant_overrides, read_plant

    twin = plant_overrides(read_plant(o.plant)) if o.plant is not None else {}
    if "vibrations.file" in overrides or "vibrations.enabled" in overrides:
        twin = {k: v for k, v in twin.items() if not k.startswith("vibrations.")}
    return twin | overrides | _run_overrides(o)


def _run_overrides(o: RunOptions) -> dict:
    """The run description's fields that `loop run`'s own options set (given ones only)."""
    values = {
        "run.duration_s": o.duration,
        "control.allow_unstable": o.allow_unstable or None,
        "auxiliary.mgm": o.mgm or None,
        "auxiliary.ogtl": o.ogtl,
        "auxiliary.period_s": o.period,
        "ncpa.rms_nm": o.ncpa,
        "ncpa.compensated": o.ncpa_offsets,
        "ncpa.offset_fraction": o.ncpa_offset_fraction,
    }
    given = {k: v for k, v in values.items() if v is not None} | common.misregistration_overrides(o.misregistration)
    return _ideal(o, given) | given | probe_overrides(o.probe_mode, o.probe_amplitude, o.probe_frequency)


IDEAL = {
    "auxiliary.ogtl": False,
    "ncpa.rms_nm": 0.0,
    "misregistration.shift_x_pitch": 0.0,
    "misregistration.shift_y_pitch": 0.0,
    "misregistration.rotation_deg": 0.0,
    "misregistration.magnification": 1.0,
    "calibration.photons_per_frame": 0.0,
    "calibration.seeing_arcsec": 0.0,
}


def _ideal(o: RunOptions, given: dict) -> dict:
    """--ideal's fields (InputError if an option sets one of them too)."""
    if not o.ideal:
        return {}
    both = sorted(k for k in given if k in IDEAL or k.startswith(("ncpa.", "misregistration.")))
    if both:
        raise InputError(f"--ideal turns OGTL and the error terms off: give it without the option that sets {both[0]}")
    return IDEAL


def _run_with_progress(request, cache, aux, sink=None):
    """``run`` with its progress on stderr (``cli.progress``)."""
    with progress.counted("closed loop", "frames", total=request.frames) as tick:
        from ..loop.run import run

        return run(request, cache, progress=tick, aux=aux, sink=sink)


def telemetry_fields(text: str | None) -> tuple[str, ...]:
    """The --telemetry-fields list (schema names; 'all'), checked."""
    if text is None:
        return DEFAULT_FIELDS
    names = PER_FRAME if text.strip() == "all" else tuple(n.strip() for n in text.split(",") if n.strip())
    unknown = [n for n in names if n not in PER_FRAME]
    if unknown or not names:
        raise InputError(
            f"--telemetry-fields: unknown field {unknown[0] if unknown else repr(text)}; accepted: {', '.join(PER_FRAME)} or all"
        )
    return tuple(dict.fromkeys(names))


def _run_streaming(request, cache, aux, writer: Hdf5Writer | None):
    """``run`` with its telemetry streamed to ``writer``, which is finished whatever happens:
    complete, or partial with the reason (divergence, an interrupt, an error); a run refused
    before its first frame leaves no file."""
    try:
        result = _run_with_progress(request, cache, aux, writer)
    except BaseException as e:
        if writer is not None:
            if isinstance(e, InputError) and writer.recorded == 0:
                writer.abandon()
            else:
                writer.finish(_stopped_by(e))
        raise
    if writer is not None:
        diverged = result.diverged_at
        writer.finish(None if diverged is None else f"the loop diverged at frame {diverged}", -1 if diverged is None else diverged)
    return result


def _stopped_by(e: BaseException) -> str:
    signum = getattr(e, "signum", None)
    if signum is not None:
        return f"interrupted by {signal.Signals(signum).name}"
    return f"stopped by an error: {type(e).__name__}: {' '.join(str(e).split())[:200]}"
