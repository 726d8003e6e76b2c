"""``soulctl optimize gains``: trial-and-error or the Modal Gain Machine, live in the simulated
loop (with the optical gain tracking loop) or offline on a recorded telemetry file."""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from .. import defaults
from ..control.gains import gains_toml, group_summary
from ..control.ogtl import PROBE_MODE as PROBE_MODE_DEFAULT
from ..control.ogtl import OgtlSettings
from ..errors import InputError
from ..files import atomic_write_text, check_output_folder, check_output_path
from ..loop.optimize import OptimizeResult, optimize
from ..loop.schedule import METHODS, OPTIMISER_OGTL, OptimizeRequest, shortest_period_s
from ..offline.mgm import MAX_WINDOW_S, REASONS, PlantInputs, offline_mgm
from ..optics.optical_gains import read_optical_gain_table
from ..plots.gains import gain_figure_names, write_gain_figures
from ..ranges import DELAY_FRAMES, EVALUATION_WINDOWS, MEASURE_S, OPTIMISATION_S, PERIOD_S, SEQUENCE_S
from ..telemetry.formats import open_telemetry, telemetry_input
from . import common, progress, quick
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
    RECORD_DELAY,
    RESONANCE,
    RUN_CONFIG,
    SEED,
    SEEING,
    TT_CONTROL,
    VIBRATIONS,
    WIND,
    array_cache,
    aux_rows,
    aux_summary,
    check_resonance,
    gain_file_input,
    loop_overrides,
    probe_overrides,
    quantity_table,
    run_description,
)
from .numbers import magnitude_option, number
from .option_table import command
from .output import console as make_console
from .output import figure_text, print_json

app = typer.Typer(no_args_is_help=True, help="Gain optimisation: trial-and-error, MGM, OGTL.")

METHOD_CHOICES = METHODS + ("both",)


def probe_settings(mode: int, amplitude: float | None, frequency: float | None) -> OgtlSettings:
    """The OGTL probe of the --probe-* options (checked by OgtlSettings)."""
    return OgtlSettings(mode=mode, amplitude_nm=amplitude, frequency_hz=frequency)


def _result_dict(result: OptimizeResult) -> dict:
    r = result.request
    tm = result.loop.telemetry
    ogtl = tm.aux_arrays("ogtl")
    return {
        "method": r.method,
        "ogtl": r.ogtl,
        "diverged_at_frame": result.diverged_at,
        "diverged_in": result.diverged_in if result.diverged_at is not None else None,
        "seconds": result.seconds,
        "phases": {k: {"first_frame": a, "end_frame": b} for k, (a, b) in result.phases.items()},
        "before": result.before.to_dict() if result.before else None,
        "after": result.after.to_dict() if result.after else None,
        "strehl_difference": _difference_dict(result),
        "sensitivity_before_after": list(result.sensitivities),
        "during_run": {k: v.to_dict() for k, v in result.during_run.items()},
        "groups": group_summary(result.gains),
        "gains": result.gains.tolist(),
        "initial_gains": result.initial_gains.tolist(),
        "sensitivity": result.loop.rtc_parameters.sensitivity,
        "optical_gain_mode": r.ogtl_settings.mode if r.ogtl else None,
        "optical_gain_estimate": float(ogtl["optical_gain"][-1]) if len(ogtl.get("optical_gain", [])) else None,
        "trial_best": [float(g) for g in tm.aux_arrays("trial").get("best", []) if math.isfinite(g)] if r.method == "trial" else None,
        "mgm_updates": len(tm.aux.get("mgm", [])),
        "safety_restores": result.safety_events,
        "optimiser_held": result.held,
        "auxiliary_summary": aux_summary({name: tm.aux_arrays(name) for name in tm.aux}),
    } | ({} if result.coupling is None else {"misregistration_stability": result.coupling.to_dict()})


def _difference_dict(result: OptimizeResult) -> dict | None:
    """after - before of the paired evaluation: mean over its windows, standard error (null with one window)."""
    if result.before is None or result.after is None:
        return None
    mean, error = result.strehl_difference()
    return {"mean": mean, "standard_error": error, "windows": result.request.windows, "window_s": result.request.window}


def _difference_text(result: OptimizeResult) -> str:
    mean, error = result.strehl_difference()
    return f"{mean:+.3f}" + (f" ± {error:.3f}" if error is not None else "")


def _render(results: dict[str, OptimizeResult], console: Console) -> None:
    first = next(iter(results.values()))
    rr = first.request.run
    obs = rr.observation
    t = Table(
        title=f"Gain optimisation: R = {obs.magnitude_r:g}, {obs.subapertures}x{obs.subapertures}, {obs.modes} modes, "
        f'{obs.frame_rate_hz:g} Hz, seeing {figure_text(rr.seeing_arcsec)}", wind {figure_text(rr.wind_m_s)} m/s',
        title_justify="left",
    )
    t.add_column("quantity")
    for method in results:
        t.add_column("trial-and-error" if method == "trial" else "MGM", justify="right")
    rows = [
        ("Strehl ratio (" + rr.band + ") before → after", lambda x: f"{x.before.strehl:.3f} → {x.after.strehl:.3f}"),
        (f"  after - before ({first.request.windows} windows)", _difference_text),
        ("  during the run (other turbulence)", lambda x: f"{x.during_run['before'].strehl:.3f} → {x.during_run['after'].strehl:.3f}"),
        ("residual before → after [nm]", lambda x: f"{x.before.residual_nm:.0f} → {x.after.residual_nm:.0f}"),
        ("Tip/Tilt jitter before → after [mas]", lambda x: f"{x.before.tt_jitter_mas:.2f} → {x.after.tt_jitter_mas:.2f}"),
    ]
    ok = {m: x for m, x in results.items() if x.diverged_at is None}
    for label, fmt in rows:
        t.add_row(label, *[fmt(x) if m in ok else "diverged" for m, x in results.items()])
    for i, g in enumerate(group_summary(first.gains)):
        t.add_row(f"gains {g['group']} (mean, min-max)", *[_group_text(group_summary(x.gains)[i]) for x in results.values()])
    t.add_row("gains Tip / Tilt", *[f"{x.gains[0]:.3f} / {x.gains[1]:.3f}" for x in results.values()])
    t.add_row(
        "slope sensitivity k", *[f"{x.loop.rtc_parameters.sensitivity:.3f}" if x.request.ogtl else "1 (no OGTL)" for x in results.values()]
    )
    for label, _ in aux_rows(first.loop.telemetry):
        t.add_row(label, *[dict(aux_rows(x.loop.telemetry)).get(label, "-") for x in results.values()])
    t.add_row("simulated / wall time [s]", *[f"{x.loop.frame / obs.frame_rate_hz:.1f} / {x.seconds:.0f}" for x in results.values()])
    console.print(t)


def _group_text(g: dict) -> str:
    return f"{g['mean']:.3f}" if g["min"] == g["max"] else f"{g['mean']:.3f} ({g['min']:.3f}-{g['max']:.3f})"


def _recorded_modes(path: Path) -> int:
    """The number of modes a record holds (the --chi-table's length without --config/--mag)."""
    with open_telemetry(path, required=()) as tm:
        if "n_modes" not in tm.dims:
            raise InputError(f"telemetry file {path} holds no modal records: --chi-table needs them (or --config/--mag)")
        return tm.dim("n_modes")


def _offline(o: GainsOptions, cache) -> int:
    telemetry, out, json_output = o.telemetry, o.out, o.json_output
    assert telemetry is not None
    observation = run_description(o.config, o.mag, {}).observation if o.config is not None or o.mag is not None else None
    gamma = None
    if o.chi_table is not None:
        n_modes = observation.modes if observation is not None else None
        gamma = read_optical_gain_table(o.chi_table, n_modes or _recorded_modes(telemetry))
    plant = PlantInputs(o.delay_frames, gamma, o.resonance)
    result = offline_mgm(telemetry, observation, cache, chi_seeing_arcsec=o.seeing, plant=plant)
    if out is not None:
        atomic_write_text(out, gains_toml(result.gains, f"MGM gains from the telemetry file {telemetry.name}"))
    if json_output:
        print_json({**result.to_dict(), "groups": group_summary(result.gains)})
        return 0
    console = make_console()
    console.print(_offline_table(result, telemetry.name, o))
    if out is not None:
        console.print(f"gains written to {out}")
    return 0


PER_MODE_ROWS = 4  # records of at most this many modes get a row per mode


def _window_reason(result) -> str:
    """Why offline MGM read from a frame after the record's first: the gains in force are the
    window's, so it starts after their last change (or k's), and it is at most 600 s long."""
    return (
        f"from frame {result.first_frame}: the frames after the last change of the gains or k (at most the last {MAX_WINDOW_S:g} s); "
        "a record at fixed gains and k gives MGM all of it"
    )


def _offline_table(result, name: str, o: GainsOptions):
    """Recorded, optimum and applied gains (per mode for a few modes, else per group), why the
    applied differ from the optimum, and the plant MGM modelled."""
    r = result
    t = quantity_table(
        f"MGM on {name}: {r.n_modes} modes, {r.rate_hz:g} Hz, delay {r.delay_frames:.3g} frames, window of {r.frames} frames "
        f"({r.frames / r.rate_hz:.2f} s, Welch segment {r.segment})" + (f"\n{_window_reason(r)}" if r.first_frame > 0 else "")
    )
    t.add_row("gains", "recorded → optimum → MGM")
    if r.n_modes <= PER_MODE_ROWS:
        for i in range(r.n_modes):
            t.add_row(f"  mode {i + 1}", f"{r.previous_gains[i]:.3f} → {r.optimum[i]:.3f} → {r.gains[i]:.3f} ({r.reasons[i]})")
    else:
        summaries = zip(group_summary(r.previous_gains), group_summary(r.optimum), group_summary(r.gains))
        for g_prev, g_opt, g in summaries:
            t.add_row(f"  {g['group']}", f"{_group_text(g_prev)} → {_group_text(g_opt)} → {_group_text(g)}")
        t.add_row("gains Tip / Tilt", f"{r.gains[0]:.3f} / {r.gains[1]:.3f}")
        counts = {reason: r.reasons.count(reason) for reason in REASONS if reason in r.reasons}
        t.add_row("why MGM's gains are not the optimum", "; ".join(f"{reason}: {n} mode(s)" for reason, n in counts.items()))
    for reason in dict.fromkeys(r.reasons):
        t.add_row(f"  {reason}", REASONS[reason])
    chi_model = (
        f"gamma_i / gamma_{r.probe_mode} (OGTL recorded, probe mode {r.probe_mode})" if r.ogtl else f"gamma_i x k (k = {r.sensitivity:.3f})"
    )
    t.add_row("chi model", chi_model)
    t.add_row("gamma_i from", str(o.chi_table) if o.chi_table is not None else r.chi_from)
    if o.delay_frames is not None:
        t.add_row("loop delay", f"{o.delay_frames:g} frames (--delay-frames)")
    for note in r.notes:
        t.add_row("note", note)
    return t


def _check_phases(duration: float | None, period: float | None, measure: float | None, sequence: float | None) -> None:
    """The phases' options, each in its range (None: the operating point's default)."""
    for value, option, accepted in (
        (duration, "--duration", OPTIMISATION_S),
        (period, "--period", PERIOD_S),
        (measure, "--measure", MEASURE_S),
        (sequence, "--sequence", SEQUENCE_S),
    ):
        if value is not None:
            accepted.check(value, option)


def _optimize_each(requests: dict[str, OptimizeRequest], cache) -> dict[str, OptimizeResult]:
    """Each method's optimisation, with its progress on stderr (``cli.progress``)."""
    results: dict[str, OptimizeResult] = {}
    for m, request in requests.items():
        with progress.counted("trial-and-error" if m == "trial" else "MGM", "frames") as tick:
            results[m] = optimize(request, cache, progress=tick)
    return results


def _gain_file_text(result: OptimizeResult) -> str:
    """The gain file of an optimisation, its operating point in the comment."""
    run = result.request.run
    obs = run.observation
    method = "MGM" if result.request.method == "mgm" else "trial-and-error"
    return gains_toml(
        result.gains,
        f'{method} gains, R = {obs.magnitude_r:g}, {obs.frame_rate_hz:g} Hz, seeing {run.seeing_arcsec:g}", seed {run.seed}',
    )


@dataclass(frozen=True)
class GainsOptions:
    """The options of `optimize gains` (an option table: see ``option_table``)."""

    method: str = typer.Option(
        "mgm",
        "--method",
        metavar="|".join(METHOD_CHOICES),
        help="MGM, trial-and-error (the three groups) or both (same seed, side by side).",
    )
    config: Path | None = RUN_CONFIG
    mag: str | None = magnitude_option(None, f"{defaults.MAGNITUDE_R:g}, the paper's bright star")
    telemetry: Path | None = typer.Option(
        None,
        "--telemetry",
        metavar="FILE|DIR",
        help="Offline: MGM on recorded telemetry (soulctl .h5, AOT .fits, an LBT Data_<TN> folder); no loop is run.",
    )
    delay_frames: float | None = RECORD_DELAY  # offline: else the record's, else the configuration's
    chi_table: Path | None = typer.Option(
        None,
        "--chi-table",
        metavar="FILE.csv",
        help="Offline: optical gains per mode ('optics gains --out' CSV) instead of the model's (a pyramid's; 1 for another sensor).",
    )
    resonance: str = RESONANCE
    seeing: float | None = SEEING
    wind: float | None = WIND
    L0: float | None = OUTER_SCALE
    duration: float | None = typer.Option(
        None,
        "--duration",
        metavar="S",
        parser=number(OPTIMISATION_S),
        show_default="5 update periods, at least 5 s",
        help=f"MGM: simulated time of the optimisation ({OPTIMISATION_S.text()}).",
    )
    period: float | None = PERIOD
    measure: float = typer.Option(
        defaults.MEASURE_S,
        "--measure",
        metavar="S",
        parser=number(MEASURE_S),
        help="Simulated time measured before and after the optimisation (in the run, and each window of the paired evaluation).",
    )
    windows: int = typer.Option(
        defaults.EVALUATION_WINDOWS,
        "--windows",
        metavar="N",
        parser=number(EVALUATION_WINDOWS),
        help=f"Consecutive windows of --measure in the paired evaluation ({EVALUATION_WINDOWS.text()}): the Strehl ratios are "
        "their mean, after - before is given with its standard error.",
    )
    sequence: float | None = typer.Option(
        None,
        "--sequence",
        metavar="S",
        parser=number(SEQUENCE_S),
        help="Trial-and-error: one closed-loop sequence per gain and pass, up and down (20 % settling; default 0.25 s, >= 100 frames).",
    )
    ogtl: bool = typer.Option(OPTIMISER_OGTL, "--ogtl/--no-ogtl", help="Run the optical gain tracking loop (slope sensitivity k).")
    probe_mode: int | None = PROBE_MODE
    probe_amplitude: float | None = PROBE_AMPLITUDE
    probe_frequency: float | None = PROBE_FREQUENCY
    tt_control: str | None = TT_CONTROL
    gains: str | None = typer.Option(
        None, "--gains", metavar="TT,MID,HIGH|FILE", help="Initial gains (default: the starting gains of 'loop run')."
    )
    band: str | None = BAND
    seed: int | None = SEED
    no_noise: bool = NO_NOISE
    vibrations: Path | None = VIBRATIONS
    no_vibrations: bool = NO_VIBRATIONS
    no_resonance: bool = NO_RESONANCE
    oversampling: int | None = common.OVERSAMPLING
    wfs_field: float | None = common.WFS_FIELD
    out: Path | None = typer.Option(
        None, "--out", metavar="GAINS.toml", help="Write the optimised gains (one per mode; 'loop run --gains' reads it)."
    )
    plot: Path | None = typer.Option(
        None, "--plot", metavar="DIR", help="Write gains.png (gain per mode) and timeseries.png (gains, k, Strehl)."
    )
    no_cache: bool = NO_CACHE
    cache_dir: Path | None = CACHE_DIR
    json_output: bool = JSON_OUTPUT


@app.command("gains")
@command(GainsOptions)
def gains_cmd(o: GainsOptions) -> int:
    """Optimise the modal gains in the simulated closed loop, or offline on a record.

    The run measures at the initial gains, runs the optimiser live as an auxiliary loop
    (trial-and-error: the three groups scanned in sequence; MGM: every mode every --period
    from the pseudo-open-loop PSDs), and measures at the optimised gains.  With --ogtl the optical gain
    tracking loop runs throughout; a safety net restores the last good gains and k when the loop degrades.  Prints the gains and the
    Strehl ratio and residual before and after, both measured in loops closed afresh on the
    run's own turbulence and noise, with --ogtl each with OGTL from k = 1 as the run, then both
    at the k the initial gains' OGTL settled to (a paired comparison; the run's own phases, at
    other times, are shown beside them); exit status 3
    only if the loop diverged all the same or the
    safety net could not recover it (no gain file written).  With
    --telemetry FILE: MGM offline on a recorded loop, printing the gains it would apply; its
    optical gains are the model's at --seeing, else at the seeing the record describes, else
    at the paper's table seeing (0.8").

    Example: soulctl optimize gains --method both --mag 10.9 --seeing 1.0 --out gains.toml --plot out/
    """
    methods = _methods(o.method)
    overrides = _checked_overrides(o, methods)
    cache = array_cache(o.no_cache, o.cache_dir)
    if o.telemetry is not None:
        if o.method != "mgm":
            raise InputError("--telemetry runs MGM offline: use it with --method mgm")
        telemetry_input(o.telemetry)
        return _offline(o, cache)
    description = run_description(o.config, o.mag, overrides).resolved()
    # its duration is not used (--duration and --measure set the phases); automatic NCPA offsets come with this command's OGTL
    run = description.request(ogtl=o.ogtl)
    probe_of_run = description.auxiliary.probe()
    period, duration, measure, sequence, windows = _phases(o, run.observation, probe_of_run)
    requests = {
        m: OptimizeRequest(
            run=run,
            method=m,
            duration_s=duration,
            period_s=period,
            ogtl=o.ogtl,
            ogtl_settings=probe_of_run,
            measure_s=measure,
            trial_sequence_s=sequence,
            windows=windows,
        )
        for m in methods
    }
    results = _optimize_each(requests, cache)
    return _report(o, results)


def _phases(o: GainsOptions, observation, probe) -> tuple[float | None, float | None, float, float | None, int]:
    """--period, --duration, --measure, --sequence and --windows as given; with SOULCTL_QUICK,
    the ones left to their defaults at their smallest (``cli.quick``): the shortest update
    period, one period of optimisation, a few frames per window and sequence."""
    if not quick.active():
        return o.period, o.duration, o.measure, o.sequence, o.windows
    rate = observation.frame_rate_hz
    period = o.period if o.period is not None else shortest_period_s(observation, probe)
    duration = o.duration if o.duration is not None else period
    measure = o.measure if o.measure != defaults.MEASURE_S else quick.MEASURE_FRAMES / rate
    sequence = o.sequence if o.sequence is not None else quick.SEQUENCE_FRAMES / rate
    windows = o.windows if o.windows != defaults.EVALUATION_WINDOWS else quick.WINDOWS
    quick.notice(
        f"update period {period:g} s, optimisation {duration:g} s, {windows} windows of {measure:.3g} s, "
        f"trial sequences of {sequence:.3g} s"
    )
    return period, duration, measure, sequence, windows


def _methods(method: str) -> list[str]:
    """The optimisers --method names."""
    if method not in METHOD_CHOICES:
        raise InputError(f"--method must be one of {', '.join(METHOD_CHOICES)}, got '{method}'")
    return list(METHODS) if method == "both" else [method]


def _checked_overrides(o: GainsOptions, methods: list[str]) -> dict:
    """Every option checked (in both modes: the offline one ignores the loop's, but one range
    per quantity) and the outputs checked before any work; the run description's overrides."""
    inputs = [("--config", o.config), ("--telemetry", o.telemetry), gain_file_input(o.gains), ("--vibrations", o.vibrations)]
    inputs.append(("--chi-table", o.chi_table))
    if o.delay_frames is not None:
        DELAY_FRAMES.check(o.delay_frames, "--delay-frames")
    check_resonance(o.resonance)
    offline_only = [name for name, given in (("--delay-frames", o.delay_frames), ("--chi-table", o.chi_table)) if given is not None]
    offline_only += ["--resonance"] if o.resonance != "auto" else []
    if o.telemetry is None and offline_only:
        raise InputError(f"{offline_only[0]} applies to offline MGM: use it with --telemetry")
    if o.out is not None:
        check_output_path(o.out, "--out", inputs)
    if o.plot is not None:
        check_output_folder(o.plot, "--plot", gain_figure_names(methods) if o.telemetry is None else ())
    overrides = loop_overrides(o)
    _check_phases(o.duration, o.period, o.measure, o.sequence)
    mode = PROBE_MODE_DEFAULT if o.probe_mode is None else o.probe_mode
    probe_settings(mode, o.probe_amplitude, o.probe_frequency)  # errors name the options
    return overrides | probe_overrides(o.probe_mode, o.probe_amplitude, o.probe_frequency)


def _report(o: GainsOptions, results: dict[str, OptimizeResult]) -> int:
    """Write the gain file and figures, print the results; the exit status (3: a loop diverged,
    the safety net could not recover it, or the final gains leave a mis-registered loop lost)."""
    failures = {m: why for m, x in results.items() if (why := x.failure()) is not None}
    final = results["mgm" if "mgm" in results else "trial"]
    if o.out is not None and not failures:
        atomic_write_text(o.out, _gain_file_text(final))
    if o.plot is not None:
        write_gain_figures(o.plot, results)
    if o.json_output:
        print_json({m: _result_dict(x) for m, x in results.items()} if o.method == "both" else _result_dict(final))
    else:
        console = make_console()
        _render(results, console)
        for m, x in results.items():
            if x.held is not None:
                console.print(f"{m}: {x.held}")
        if o.out is not None and not failures:
            console.print(f"gains written to {o.out}")
        if o.plot is not None:
            console.print(f"figures written to {o.plot}/")
    for m, why in failures.items():
        print(f"soulctl: {why} during the {m} optimisation; no gain file written", file=sys.stderr)
    return 3 if failures else 0
