"""``soulctl loop run``: a simulated SOUL closed loop, from a guide star to Strehl and jitter."""

from __future__ import annotations

import dataclasses
import json
import math
import sys
from contextlib import nullcontext
from pathlib import Path

import typer
from rich.console import Console

from ..control.ogtl import OgtlSettings
from ..control.structure import StructuralResonance
from ..errors import InputError
from ..files import check_output_path, read_toml
from ..loop.metrics import BANDS
from ..loop.run import RunRequest, run
from ..loop.simulation import DEFAULT_FORGETTING, LoopGains
from ..loop.optimize import LiveOptimisers
from ..loop.telemetry_file import telemetry_arrays, write_telemetry
from ..observation import Observation, observation_for_magnitude
from ..optics.atmosphere import SEEING_RANGE_ARCSEC
from ..plots.loop import write_loop_figures
from .configure import parse_magnitude
from .common import (BAND, CACHE_DIR, CONFIG, JSON_OUTPUT, NO_CACHE, NO_NOISE, NO_RESONANCE, NO_VIBRATIONS, OUTER_SCALE, OVERSAMPLING,
                     PERIOD, PROBE_AMPLITUDE, PROBE_FREQUENCY, PROBE_MODE, SEED, SEEING, TT_CONTROL, VIBRATIONS, WIND, array_cache,
                     frames_progress, observation_option, quantity_table, vibration_spectrum)

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
    """``TT,MID,HIGH`` (the paper's three groups) or a gain file: TOML with ``gains = [...]``
    (one per mode), or text/CSV with one gain per line (``mode,gain`` lines accepted)."""
    if text is None:
        return None
    path = Path(text)
    if path.suffix.lower() in (".toml", ".txt", ".csv", ".dat") or path.exists():
        if path.suffix.lower() == ".toml":
            values = read_toml(path, "gain file").get("gains")
            if not isinstance(values, list):
                raise InputError(f"gain file {path} needs a list 'gains = [...]' with one gain per mode")
        else:
            try:
                lines = [ln.strip() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]
            except OSError as e:
                raise InputError(f"cannot read gain file {path}: {e.strerror or e}") from None
            values = [ln.split(",")[-1] for ln in lines if not ln.lower().startswith("mode")]
        try:
            gains = [float(v) for v in values]
        except (TypeError, ValueError):
            raise InputError(f"gain file {path}: every gain must be a number") from None
        if not all(math.isfinite(g) and g >= 0 for g in gains):
            raise InputError(f"gain file {path}: gains must be numbers >= 0")
        return LoopGains.from_modes(gains, forgetting)
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 3 or not all(math.isfinite(v) and v >= 0 for v in values):
        raise InputError(f"--gains must be TT,MID,HIGH (three numbers >= 0) or a gain file, got '{text}'")
    return LoopGains(*values, forgetting=forgetting)


def _check_number(name: str, value: float, lo: float, hi: float, unit: str) -> None:
    if not (math.isfinite(value) and lo < value <= hi):
        raise InputError(f"{name} must be in {lo:g}..{hi:g} {unit} (> {lo:g}), got {value:g}")


def check_conditions(seeing: float, wind: float, L0: float, band: str) -> None:
    """InputError naming the option and its range for --seeing, --wind, --L0, --band."""
    lo, hi = SEEING_RANGE_ARCSEC
    if not (math.isfinite(seeing) and lo <= seeing <= hi):
        raise InputError(f"--seeing must be in {lo:g}..{hi:g} arcsec, got {seeing:g}")
    _check_number("--wind", wind, 0.0, 100.0, "m/s")
    _check_number("--L0", L0, 0.0, 1e4, "m")
    if band not in BANDS:
        raise InputError(f"unknown band '{band}': accepted {', '.join(BANDS)}")


def _result_dict(result) -> dict:
    m = result.metrics
    d = {
        "configuration": result.configuration(),
        "calibration": {"valid_subapertures": result.calibration.interaction_matrix.shape[0] // 2,
                        "modes": result.calibration.basis.n_modes, "from_cache": result.calibration.from_cache,
                        "seconds": result.calibration_seconds},
        "seconds": result.seconds,
        "frames_per_second": len(result.telemetry.residual_rms_nm) / result.seconds if result.seconds > 0 else None,
        "diverged_at_frame": result.diverged_at,
        "metrics": None,
    }
    if result.telemetry.aux:
        d["auxiliary_loops"] = sorted(result.telemetry.aux)
        d["final_gains"] = result.final_gains.tolist()
        d["final_sensitivity"] = result.final_sensitivity
    if m is not None:
        d["metrics"] = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in m.to_dict().items()}
    return d


def _render(result, console: Console) -> None:
    r, m = result.request, result.metrics
    obs = r.observation
    t = quantity_table(f"Closed loop: R = {obs.magnitude_r:g}, {obs.subapertures}x{obs.subapertures}, {obs.modes} modes, "
                       f"{obs.frame_rate_hz:g} Hz, seeing {r.seeing_arcsec:g}\", {r.duration_s:g} s")
    g = result.gains
    t.add_row("Tip/Tilt control", f"{'IIR' if obs.tt_control == 'iir' else 'integrator'}, gain {g.tip_tilt:.3g}")
    t.add_row("gains modes 3-120 / 121-last", f"{g.mid:.3g} / {g.high:.3g}" + (" (gain file)" if g.modes else ""))
    t.add_row(f"Strehl ratio ({r.band}, {BANDS[r.band] * 1e6:.3g} µm)", f"{m.strehl:.3f}")
    t.add_row("Tip/Tilt jitter, residual (per axis)", f"{m.tt_jitter_mas:.2f} mas")
    t.add_row("Tip/Tilt jitter, pseudo-open loop (all / > 3 Hz)", f"{m.tt_jitter_pol_mas:.2f} / {m.tt_jitter_pol_3hz_mas:.2f} mas")
    t.add_row("residual wavefront error", f"{m.residual_nm:.0f} nm RMS")
    t.add_row("rejection at 13 Hz (telemetry)", "n/a (run too short)" if not math.isfinite(m.rejection_13hz) else f"{m.rejection_13hz:.3f}")
    t.add_row("frames (metrics on)", f"{m.frames} ({m.frames - m.skipped_frames})")
    if result.telemetry.aux:
        fg = result.final_gains
        t.add_row("auxiliary loops", ", ".join(sorted(result.telemetry.aux)))
        t.add_row("final gains Tip / Tilt / 3-120 / 121-last", f"{fg[0]:.3f} / {fg[1]:.3f} / {fg[2:120].mean():.3f} / "
                  + (f"{fg[120:].mean():.3f}" if len(fg) > 120 else "-"))
        t.add_row("final slope sensitivity k", f"{result.final_sensitivity:.3f}")
    t.add_row("simulation speed", f"{m.frames / result.seconds:.0f} frames/s")
    console.print(t)


@app.command("run")
def run_cmd(
    config: Path | None = CONFIG,
    mag: str | None = typer.Option(None, "--mag", metavar="R", help=f"Guide star R magnitude (default {DEFAULT_MAGNITUDE}, the paper's bright star)."),
    seeing: float = SEEING,
    wind: float = WIND,
    L0: float = OUTER_SCALE,
    duration: float = typer.Option(0.2, "--duration", metavar="S", help="Simulated time (s); the first 20 % is left out of the metrics."),
    tt_control: str | None = TT_CONTROL,
    gains: str | None = typer.Option(None, "--gains", metavar="TT,MID,HIGH|FILE", help="Gains of modes 1-2, 3-120, 121-last, or a per-mode gain file."),
    band: str = BAND,
    seed: int = SEED,
    no_noise: bool = NO_NOISE,
    vibrations: Path | None = VIBRATIONS,
    no_vibrations: bool = NO_VIBRATIONS,
    no_resonance: bool = NO_RESONANCE,
    oversampling: int = OVERSAMPLING,
    allow_unstable: bool = typer.Option(False, "--allow-unstable", help="Run gains the analysis calls unstable."),
    mgm: bool = typer.Option(False, "--mgm", help="Run the Modal Gain Machine beside the loop (from the initial gains, every --period)."),
    ogtl: bool = typer.Option(False, "--ogtl", help="Run the optical gain tracking loop beside the loop (probe on --probe-mode)."),
    period: float = PERIOD,
    probe_mode: int = PROBE_MODE,
    probe_amplitude: float = PROBE_AMPLITUDE,
    probe_frequency: float | None = PROBE_FREQUENCY,
    telemetry: Path | None = typer.Option(None, "--telemetry", metavar="FILE.h5", help="Write the telemetry (HDF5; with the auxiliary loops' records)."),
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
    check_conditions(seeing, wind, L0, band)
    _check_number("--duration", duration, 0.0, 600.0, "s")
    if telemetry is not None:
        check_output_path(telemetry, "--telemetry")
    if plot is not None and not plot.is_dir():
        raise InputError(f"--plot must be an existing folder, got {plot}")
    obs = observation_from(config, mag, tt_control)
    loop_gains = parse_gains(gains, DEFAULT_FORGETTING)
    vib = vibration_spectrum(no_vibrations, vibrations)
    request = RunRequest(obs, seeing, wind, L0, duration, loop_gains, band, seed, not no_noise, vib, oversampling,
                         None if no_resonance else StructuralResonance(), allow_unstable)
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
        write_telemetry(telemetry, tm, {"rate_hz": obs.frame_rate_hz, "delay_frames": obs.delay_frames,
                                        "n_modes": result.calibration.basis.n_modes,
                                        "diverged_at": -1 if result.diverged_at is None else result.diverged_at},
                        result.configuration())
    if result.diverged_at is not None:
        message = f"loop diverged at frame {result.diverged_at} (residual {result.diverged_residual_nm:.0f} nm RMS)"
        if json_output:
            print(json.dumps(_result_dict(result)))
        print(f"soulctl: {message}" + (f"; telemetry written to {telemetry}" if telemetry else ""), file=sys.stderr)
        return 3
    if plot is not None:
        write_loop_figures(plot, result)
    if json_output:
        print(json.dumps(_result_dict(result)))
    else:
        console = Console()
        _render(result, console)
        if telemetry is not None:
            console.print(f"telemetry written to {telemetry}")
        if plot is not None:
            console.print(f"figures written to {plot}/")
    return 0
