"""``soulctl loop run``: a simulated SOUL closed loop, from a guide star to Strehl and jitter."""

from __future__ import annotations

import dataclasses
import sys
from contextlib import nullcontext
from pathlib import Path

import typer
from rich.console import Console

from ..control.gain_file import SUFFIXES, read_gain_file
from ..control.ogtl import OgtlSettings
from ..control.structure import StructuralResonance
from ..control.trial import MID_GROUP_END
from ..errors import InputError
from ..files import check_output_folder, check_output_path
from ..loop.metrics import BANDS
from ..loop.optimize import LiveOptimisers
from ..loop.run import RunRequest, run
from ..loop.simulation import DEFAULT_FORGETTING, LoopGains
from ..loop.telemetry_file import telemetry_arrays, write_telemetry
from ..observation import Observation, observation_for_magnitude
from ..plots.loop import LOOP_FIGURES, write_loop_figures
from ..ranges import DURATION_S, LOOP_GAIN, OVERSAMPLING
from . import common
from .common import (
    BAND,
    CACHE_DIR,
    CONFIG,
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
    SEED,
    SEEING,
    TT_CONTROL,
    VIBRATIONS,
    WIND,
    array_cache,
    aux_rows,
    aux_summary,
    check_run_options,
    frames_progress,
    observation_option,
    quantity_table,
    vibration_spectrum,
)
from .configure import parse_magnitude
from .numbers import number
from .output import console as make_console
from .output import print_json, styled

app = typer.Typer(no_args_is_help=True, help="The simulated closed loop.")

DEFAULT_MAGNITUDE = "9.7"  # the paper's bright-star on-sky tests


def observation_from(config: Path | None, mag: str | None, tt_control: str | None) -> Observation:
    """--config or --mag (the default star without either), with --tt-control applied."""
    obs = observation_option(config, mag) or observation_for_magnitude(parse_magnitude(DEFAULT_MAGNITUDE))
    if tt_control is None or tt_control == obs.tt_control:
        return obs
    if tt_control == "int":
        return dataclasses.replace(obs, tt_control="int", tt_zeros=(), tt_poles=(), tt_filter_rate_hz=None)
    if tt_control == "iir":
        raise InputError(f"--tt-control iir: the roots table has no IIR filter at {obs.frame_rate_hz:g} Hz (750 Hz and above)")
    raise InputError(f"--tt-control must be 'iir' or 'int', got '{tt_control}'")


def parse_gains(text: str | None, forgetting: float) -> LoopGains | None:
    """``TT,MID,HIGH`` (the paper's three groups) or a per-mode gain file
    (``control.gain_file``: TOML ``gains = [...]``, or text/CSV lines)."""
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
    return LoopGains(*values, forgetting=forgetting)


def _gain_file(text: str) -> Path | None:
    """--gains as a gain file (a gain file's suffix, or an existing path), else None (groups)."""
    path = Path(text)
    return path if path.suffix.lower() in SUFFIXES or path.exists() else None


def gain_file_input(text: str | None) -> tuple[str, Path | None]:
    """--gains as an input file of the command (for the output checks), or None."""
    return ("--gains", None if text is None else _gain_file(text))


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
    if result.telemetry.aux:
        d["auxiliary_loops"] = sorted(result.telemetry.aux)
        d["final_gains"] = result.final_gains.tolist()
        d["final_sensitivity"] = result.final_sensitivity
        d["auxiliary_summary"] = aux_summary({name: result.telemetry.aux_arrays(name) for name in result.telemetry.aux})
    return d


def _value(x, spec: str, unit: str = "") -> str:
    """A metric as the table shows it; 'n/a (run too short)' when it is not available."""
    return "n/a (run too short)" if x is None else format(x, spec) + unit


def _render(result, console: Console) -> None:
    r, m = result.request, result.metrics
    obs = r.observation
    t = quantity_table(
        f"Closed loop: R = {obs.magnitude_r:g}, {obs.subapertures}x{obs.subapertures}, {obs.modes} modes, "
        f'{obs.frame_rate_hz:g} Hz, seeing {r.seeing_arcsec:g}", {r.duration_s:g} s'
    )
    g = result.gains
    t.add_row("Tip/Tilt control", f"{'IIR' if obs.tt_control == 'iir' else 'integrator'}, gain {g.tip_tilt:.3g}")
    if obs.modes > MID_GROUP_END:
        t.add_row(
            f"gains modes 3-{MID_GROUP_END} / {MID_GROUP_END + 1}-last", f"{g.mid:.3g} / {g.high:.3g}" + (" (gain file)" if g.modes else "")
        )
    else:
        t.add_row(f"gains modes 3-{obs.modes}", f"{g.mid:.3g}" + (" (gain file)" if g.modes else ""))
    t.add_row(f"Strehl ratio ({r.band}, {BANDS[r.band] * 1e6:.3g} µm)", _value(m.strehl, ".3f"))
    t.add_row("Tip/Tilt jitter, residual (per axis)", _value(m.tt_jitter_mas, ".2f", " mas"))
    t.add_row(
        "Tip/Tilt jitter, pseudo-open loop (all / > 3 Hz)",
        f"{_value(m.tt_jitter_pol_mas, '.2f', ' mas')} / {_value(m.tt_jitter_pol_3hz_mas, '.2f', ' mas')}",
    )
    t.add_row("residual wavefront error", _value(m.residual_nm, ".0f", " nm RMS"))
    t.add_row("rejection at 13 Hz (telemetry)", _value(m.rejection_13hz, ".3f"))
    t.add_row("frames (metrics on)", f"{m.frames} ({m.frames - m.skipped_frames})")
    if result.telemetry.aux:
        fg = result.final_gains
        t.add_row("auxiliary loops", ", ".join(sorted(result.telemetry.aux)))
        t.add_row(
            "final gains Tip / Tilt / 3-120 / 121-last",
            f"{fg[0]:.3f} / {fg[1]:.3f} / {fg[2:120].mean():.3f} / " + (f"{fg[120:].mean():.3f}" if len(fg) > 120 else "-"),
        )
        t.add_row("final slope sensitivity k", f"{result.final_sensitivity:.3f}")
        for label, text in aux_rows(result.telemetry):
            t.add_row(label, text)
    t.add_row("simulation speed", f"{m.frames / result.seconds:.0f} frames/s" if result.seconds > 0 else "n/a")
    console.print(t)
    for note in result.notes:
        console.print(styled(f"note: {note}", "dim"))


@app.command("run")
def run_cmd(
    config: Path | None = CONFIG,
    mag: str | None = typer.Option(
        None, "--mag", metavar="R", help=f"Guide star R magnitude (default {DEFAULT_MAGNITUDE}, the paper's bright star)."
    ),
    seeing: float = SEEING,
    wind: float = WIND,
    L0: float = OUTER_SCALE,
    duration: float = typer.Option(
        0.2, "--duration", parser=number(DURATION_S), metavar="S", help="Simulated time (s); the first 20 % is left out of the metrics."
    ),
    tt_control: str | None = TT_CONTROL,
    gains: str | None = typer.Option(
        None, "--gains", metavar="TT,MID,HIGH|FILE", help="Gains of modes 1-2, 3-120, 121-last, or a per-mode gain file."
    ),
    band: str = BAND,
    seed: int = SEED,
    no_noise: bool = NO_NOISE,
    vibrations: Path | None = VIBRATIONS,
    no_vibrations: bool = NO_VIBRATIONS,
    no_resonance: bool = NO_RESONANCE,
    oversampling: int = common.OVERSAMPLING,
    allow_unstable: bool = typer.Option(False, "--allow-unstable", help="Run gains the analysis calls unstable."),
    mgm: bool = typer.Option(False, "--mgm", help="Run the Modal Gain Machine beside the loop (from the initial gains, every --period)."),
    ogtl: bool = typer.Option(False, "--ogtl", help="Run the optical gain tracking loop beside the loop (probe on --probe-mode)."),
    period: float | None = PERIOD,
    probe_mode: int = PROBE_MODE,
    probe_amplitude: float | None = PROBE_AMPLITUDE,
    probe_frequency: float | None = PROBE_FREQUENCY,
    telemetry: Path | None = typer.Option(
        None, "--telemetry", metavar="FILE.h5", help="Write the telemetry (HDF5; with the auxiliary loops' records)."
    ),
    plot: Path | None = typer.Option(None, "--plot", metavar="DIR", help="Write psf.png, jitter.png, modal_variance.png."),
    no_cache: bool = NO_CACHE,
    cache_dir: Path | None = CACHE_DIR,
    json_output: bool = JSON_OUTPUT,
) -> int:
    """Close a simulated SOUL loop: LBT turbulence and vibrations, the adaptive secondary with
    its 127 Hz structural resonance, the modulated pyramid with detector noise, the C++ slopes
    and RTC, the loop delay.  Prints the Strehl ratio, Tip/Tilt jitter (residual and
    pseudo-open loop), residual wavefront error and the 13 Hz rejection.  --mgm and --ogtl run
    the Modal Gain Machine and the optical gain tracking loop beside it once the loop has
    closed (their records go to the telemetry file).  Exit status 3 if the loop diverges (the
    telemetry so far is still written).

    Example: soulctl loop run --mag 9.7 --seeing 1.0 --duration 1 --plot out/
    """
    check_run_options(seeing, wind, L0, band, seed, duration)
    OVERSAMPLING.check(oversampling, "--oversampling")
    inputs = [("--config", config), gain_file_input(gains), ("--vibrations", vibrations)]
    if telemetry is not None:
        check_output_path(telemetry, "--telemetry", inputs)
    if plot is not None:
        check_output_folder(plot, "--plot", LOOP_FIGURES)
    obs = observation_from(config, mag, tt_control)
    loop_gains = parse_gains(gains, DEFAULT_FORGETTING)
    vib = vibration_spectrum(no_vibrations, vibrations)
    request = RunRequest(
        obs,
        seeing,
        wind,
        L0,
        duration,
        loop_gains,
        band,
        seed,
        not no_noise,
        vib,
        oversampling,
        None if no_resonance else StructuralResonance(),
        allow_unstable,
    )
    aux = None
    if mgm or ogtl:
        aux = LiveOptimisers(mgm, ogtl, period, OgtlSettings(probe_mode, probe_amplitude, probe_frequency))
        aux.check(obs, duration)
    cache = array_cache(no_cache, cache_dir)
    show = not json_output and sys.stderr.isatty()
    progress = frames_progress("closed loop")
    with progress if show else nullcontext():
        task = progress.add_task("loop", total=request.frames) if show else None
        result = run(request, cache, progress=(lambda k: progress.update(task, completed=k)) if show else None, aux=aux)
    if telemetry is not None:
        tm = telemetry_arrays(result.telemetry)
        tm["gains"] = result.final_gains
        write_telemetry(
            telemetry,
            tm,
            {
                "rate_hz": obs.frame_rate_hz,
                "delay_frames": obs.delay_frames,
                "n_modes": result.calibration.basis.n_modes,
                "diverged_at": -1 if result.diverged_at is None else result.diverged_at,
            },
            result.configuration(),
        )
    if result.diverged_at is not None:
        message = f"loop diverged at frame {result.diverged_at} (residual {result.diverged_residual_nm:.0f} nm RMS)"
        if json_output:
            print_json(_result_dict(result))
        print(f"soulctl: {message}" + (f"; telemetry written to {telemetry}" if telemetry else ""), file=sys.stderr)
        return 3
    if plot is not None:
        write_loop_figures(plot, result)
    if json_output:
        print_json(_result_dict(result))
    else:
        console = make_console()
        _render(result, console)
        if telemetry is not None:
            console.print(f"telemetry written to {telemetry}")
        if plot is not None:
            console.print(f"figures written to {plot}/")
    return 0
