"""``soulctl filter analyze|design``: temporal control filters, their margins and rejection, and
the Tip/Tilt IIR design (paper, Sec. 2.3)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import typer
from rich import box
from rich.console import Console
from rich.table import Table

from .. import __version__, defaults, tables
from ..control.delay import DelayModel
from ..control.design import DesignResult, Disturbance, design_tt_filter, roots_table_csv
from ..control.filters import Filter
from ..control.transfer import RESONANCE_HZ, UNSTABLE_NOTE, VIBRATION_HZ, Loop, LoopAnalysis, Plant, analyze
from ..disturbance.turbulence import TurbulenceTipTilt
from ..disturbance.vibrations import VibrationSpectrum
from ..errors import InputError
from ..files import atomic_write_text, check_output_path, same_file
from ..identify.plant import plant_disturbance, read_plant
from ..ranges import (
    ANALYSIS_GAIN,
    ANALYSIS_RATE_HZ,
    DELAY_FRAMES,
    DESIGN_DELAY_FRAMES,
    DESIGN_RATE_HZ,
    EPSILON,
    FORGETTING,
    MAX_CONTROLLERS,
    MAX_DESIGN_RATES,
    NOISE_MAS,
    OPTICAL_GAIN,
    ROOT_MODULUS,
    SEED,
    Range,
)
from . import progress
from .common import outer_scale_option, seeing_option, wind_option
from .numbers import number
from .option_table import command
from .output import JSON_OUTPUT, figure_text, print_json, styled
from .output import console as make_console

app = typer.Typer(help="Analyse and design temporal control filters (margins, rejection, the Tip/Tilt IIR design).", no_args_is_help=True)

UNSTABLE_EXIT = 3  # an analysed loop is unstable (its figures are still printed)
N_ROOTS_MAX = 8  # zeros or poles of a controller given by its roots
MAX_LABEL = 80  # characters of a controller's name (a table column, a legend entry)
CONTROLS = ("iir", "int", "leaky")
SYSTEMS = ("soul", "flao")


# ---------------------------------------------------------------- argument parsing


def _values(text: str, option: str, kind: str, limit: int = MAX_CONTROLLERS) -> list[str]:
    items = [t.strip() for t in str(text).split(",")]
    if not items or any(t == "" for t in items):
        raise InputError(f"{option} must be a comma-separated list of {kind}, got '{text}'")
    if len(items) > limit:
        raise InputError(f"{option} lists {len(items)} values: accepted at most {limit}")
    return items


def _numbers(text: str, option: str, accepted: Range, limit: int = MAX_CONTROLLERS) -> list[float]:
    """Comma-separated numbers, each in ``accepted``."""
    return [accepted.parse(t, option) for t in _values(text, option, "numbers", limit)]


def _roots(text: str | None, option: str) -> tuple[complex, ...]:
    if text is None or text.strip() == "":
        return ()
    out = []
    for t in _values(text, option, "roots", limit=N_ROOTS_MAX):
        try:
            v = complex(t.replace(" ", ""))
        except ValueError:
            raise InputError(f"{option} must be numbers such as 0.5 or 0.5+0.2j, got '{t}'") from None
        if not (math.isfinite(v.real) and math.isfinite(v.imag) and abs(v) <= ROOT_MODULUS):
            raise InputError(f"{option} must be numbers of modulus at most {ROOT_MODULUS:g}, got '{t}'")
        out.append(v.real if v.imag == 0 else v)
    return tuple(out)


def _broadcast(lists: dict[str, list]) -> int:
    """The number of controllers: every list has one value or that many."""
    n = max(len(v) for v in lists.values())
    for name, v in lists.items():
        if len(v) not in (1, n):
            longest = max(lists, key=lambda k: len(lists[k]))
            raise InputError(f"{name} has {len(v)} values but {longest} has {n}: give one value or {n}")
    return n


def _pick(values: list, i: int):
    return values[i] if len(values) > 1 else values[0]


# ---------------------------------------------------------------- analyze


@dataclass(frozen=True)
class AnalyzedLoop:
    label: str
    control: str
    description: str
    delay_ms: float
    loop: Loop
    analysis: LoopAnalysis

    def to_dict(self) -> dict:
        f = self.loop.controller
        return {
            "label": self.label,
            "control": self.control,
            "filter": self.description,
            "zeros": [_json_root(z) for z in f.zeros],
            "poles": [_json_root(p) for p in f.poles],
            "delay_ms": self.delay_ms,
            **self.analysis.to_dict(),
        }


def _json_root(r: complex):
    r = complex(r)
    return r.real if r.imag == 0 else [r.real, r.imag]


def _controller(control: str, gain: float, rate: float, forgetting: float, zeros: tuple, poles: tuple) -> tuple[Filter, str]:
    if control == "int":
        return Filter.integrator(gain), "integrator"
    if control == "leaky":
        return Filter.leaky(forgetting, gain), f"leaky (α = {forgetting:g})"
    if poles:
        return Filter.iir(zeros, poles, gain), "IIR (given roots)"
    row = tables.nearest_roots(rate, tables.tt_iir_table(), "the roots table (give --zeros/--poles for another rate)")
    return Filter.iir(row.zeros, row.poles, gain), f"IIR (table {row.frame_rate_hz:g} Hz)"


def _fmt(x, spec: str = ".3g", none: str = "—") -> str:
    if x is None:
        return none
    if isinstance(x, float) and math.isinf(x):
        return "∞"
    return format(x, spec)


def _render_analysis(loops: list[AnalyzedLoop], console: Console) -> None:
    t = Table(title="Loop analysis: P(z) = χ z^-d, L = H P, S = 1/(1+L), T = L/(1+L)", title_justify="left")
    t.add_column("")
    for a in loops:
        t.add_column(a.label, justify="right")

    def row(name, fn):
        t.add_row(name, *[fn(a) for a in loops])

    row("controller", lambda a: a.description)
    row("frame rate", lambda a: f"{a.analysis.rate_hz:g} Hz")
    row("gain", lambda a: figure_text(a.analysis.gain))
    row("delay", lambda a: f"{a.delay_ms:.3g} ms = {a.analysis.delay_frames:.3f} fr")
    row("optical gain χ", lambda a: figure_text(a.analysis.optical_gain))
    row("verdict", lambda a: styled("stable", "green") if a.analysis.stable else styled("UNSTABLE", "bold red"))
    row("gain margin", lambda a: _fmt(a.analysis.gain_margin, ".2f"))
    row("phase margin", lambda a: _fmt(a.analysis.phase_margin_deg, ".1f") + "°" if a.analysis.phase_margin_deg is not None else "—")
    row("modulus margin min|1+L|", lambda a: _closed(a.analysis, "modulus_margin", _at_frequency(a.analysis)))
    row("max stable gain", lambda a: _fmt(a.analysis.max_stable_gain, ".3f"))
    row("|S(13 Hz)| rejection", lambda a: _closed(a.analysis, "rejection_13hz", lambda x: f"{x:.3f}"))
    row("|T(127 Hz)|", lambda a: _closed(a.analysis, "noise_127hz", lambda x: f"{x:.3f}"))
    row("|S| -3 dB (rejection bw)", lambda a: _closed(a.analysis, "rejection_bandwidth_hz", lambda x: f"{x:.1f} Hz"))
    row("|T| -3 dB bandwidth", lambda a: _closed(a.analysis, "bandwidth_hz", lambda x: f"{x:.1f} Hz"))
    console.print(t)
    if any(a.analysis.not_available() for a in loops):
        console.print(f"n/a (unstable): {UNSTABLE_NOTE}; lower the gain below the maximum stable gain.", style="dim")


def _at_frequency(analysis):
    return lambda x: f"{x:.3f} @ {analysis.modulus_margin_hz:.0f} Hz"


def _closed(analysis, name: str, text) -> str:
    """A closed-loop figure's cell: n/a for an unstable loop, — where it does not exist."""
    if analysis.not_available():
        return "n/a (unstable)"
    value = analysis.figure(name)
    return "—" if value is None else text(value)


@dataclass(frozen=True)
class AnalyzeOptions:
    """The options of `filter analyze` (an option table: see ``option_table``)."""

    rate: str | None = typer.Option(
        None, "--rate", metavar="HZ[,HZ…]", help=f"Frame rate(s) in Hz ({ANALYSIS_RATE_HZ.text()}); required without --plant."
    )
    control: str = typer.Option("iir", "--control", metavar="iir|int|leaky[,…]", help="Controller(s).")
    gain: str = typer.Option(..., "--gain", metavar="G[,G…]", help=f"Loop gain(s) ({ANALYSIS_GAIN.text()}).")
    delay_frames: str | None = typer.Option(
        None, "--delay-frames", metavar="D[,D…]", help=f"Loop delay in frames ({DELAY_FRAMES.text()}, fractional allowed)."
    )
    delay_ms: str | None = typer.Option(
        None, "--delay-ms", metavar="T[,T…]", help=f"Loop delay in ms (>= 0; at most {DELAY_FRAMES.hi:g} frames at the rate)."
    )
    system: str = typer.Option(
        "soul", "--system", metavar="soul|flao[,…]", help="Delay model when no delay is given (tables/delay_model.toml)."
    )
    chi: str | None = typer.Option(
        None,
        "--chi",
        metavar="X[,X…]",
        help=f"Optical gain χ of the plant ({OPTICAL_GAIN.text()}; default 1, with --plant its Tip/Tilt χ).",
    )
    plant: Path | None = typer.Option(
        None, "--plant", metavar="PLANT.toml", help="Identified plant ('telemetry identify --out'): its rate, delay and Tip/Tilt χ."
    )
    forgetting: str = typer.Option("0.99", "--forgetting", metavar="A[,A…]", help="Forgetting factor of 'leaky' (0..1).")
    zeros: str | None = typer.Option(
        None,
        "--zeros",
        metavar="B1,B2,…",
        help=f"IIR zeros (default: the roots table; modulus <= {ROOT_MODULUS:g}, at most {N_ROOTS_MAX}).",
    )
    poles: str | None = typer.Option(
        None, "--poles", metavar="A1,A2,…", help=f"IIR poles, at least one (modulus <= {ROOT_MODULUS:g}, at most {N_ROOTS_MAX})."
    )
    label: str | None = typer.Option(None, "--label", metavar="NAME[,NAME…]", help="Names of the controllers in the table and plot.")
    json_output: bool = JSON_OUTPUT
    plot: Path | None = typer.Option(None, "--plot", metavar="FILE.png", help="Write |S|, |T| and the Nyquist plot.")


@command(AnalyzeOptions)
def analyze_command(o: AnalyzeOptions) -> int:
    """Margins, rejection and bandwidth of one or more control loops.

    Lists (comma-separated, at most 16) compare controllers side by side: each option takes one
    value or one per controller.  Prints the gain, phase and modulus margins, the maximum stable gain,
    |S(13 Hz)|, |T(127 Hz)|, the -3 dB bandwidths and a stable/unstable verdict.  Exit status 3
    if any loop is unstable (its figures are still printed).

    Example (the paper's Fig. IIR1700TF): soulctl filter analyze --rate 1700,1700,1000
    --control iir,int,int --gain 0.69,0.21,0.39 --system soul,soul,flao
    --label SOUL-IIR,SOUL-INT,FLAO-INT --plot tf.png
    """
    loops = _analyzed_loops(o)
    if o.plot is not None:
        from ..plots.figure import save_figure
        from ..plots.transfer import Curve, transfer_figure

        save_figure(transfer_figure([Curve(a.label, a.loop) for a in loops]), o.plot)
    all_stable = all(a.analysis.stable for a in loops)
    if o.json_output:
        print_json(
            {"controllers": [a.to_dict() for a in loops], "stable": all_stable, "vibration_hz": VIBRATION_HZ, "resonance_hz": RESONANCE_HZ}
        )
    else:
        console = make_console()
        _render_analysis(loops, console)
        if o.plot is not None:
            console.print(f"written {o.plot}")
        if not all_stable:
            console.print(styled("at least one loop is unstable (exit status 3)", "bold red"))
    return 0 if all_stable else UNSTABLE_EXIT


def _with_plant(o: AnalyzeOptions) -> AnalyzeOptions:
    """The options with --plant's rate (unless --rate), delay and Tip/Tilt chi (unless --chi)."""
    if o.plant is None:
        if o.rate is None:
            raise InputError("give --rate (or --plant, an identified plant with its rate)")
        return replace(o, chi=o.chi or "1")
    if o.delay_frames is not None or o.delay_ms is not None:
        raise InputError("--plant gives the delay: drop --delay-frames/--delay-ms (or --plant)")
    plant = read_plant(o.plant)
    chi = o.chi or repr(float(plant.chi(2)[0]))
    return replace(o, rate=o.rate or repr(plant.rate_hz), delay_frames=repr(plant.delay.value), chi=chi)


def _analyzed_loops(o: AnalyzeOptions) -> list[AnalyzedLoop]:
    """The controllers of `filter analyze`, every option checked (and --plot) before any work."""
    o = _with_plant(o)
    if o.delay_frames is not None and o.delay_ms is not None:
        raise InputError("give --delay-frames or --delay-ms, not both")
    if o.plot is not None:
        check_output_path(o.plot, "--plot")
        from ..plots.figure import plot_format

        plot_format(o.plot)
    lists = _analysis_lists(o.rate, o.control, o.gain, o.system, o.chi, o.forgetting, o.delay_frames, o.delay_ms, o.label)
    z, p = _roots(o.zeros, "--zeros"), _roots(o.poles, "--poles")
    if (o.zeros is not None or o.poles is not None) and not p:
        raise InputError("--poles needs at least one pole (a control filter is an IIR filter)")
    if p and "iir" not in lists["--control"]:
        raise InputError("--zeros/--poles apply to --control iir")
    n = _broadcast(lists)
    return [_analyzed(lists, i, z, p) for i in range(n)]


def _analysis_lists(rate, control, gain, system, chi, forgetting, delay_frames, delay_ms, label) -> dict[str, list]:
    """The comma lists of `filter analyze`, each checked (one controller per position, see
    ``_broadcast``)."""
    lists: dict[str, list] = {
        "--rate": _numbers(rate, "--rate", ANALYSIS_RATE_HZ),
        "--control": _values(control.lower(), "--control", "controls"),
        "--gain": _numbers(gain, "--gain", ANALYSIS_GAIN),
        "--system": _values(system.lower(), "--system", "delay models"),
        "--chi": _numbers(chi, "--chi", OPTICAL_GAIN),
        "--forgetting": _numbers(forgetting, "--forgetting", FORGETTING),
    }
    for c in lists["--control"]:
        if c not in CONTROLS:
            raise InputError(f"--control must be iir, int or leaky, got '{c}'")
    for s in lists["--system"]:
        if s not in SYSTEMS:
            raise InputError(f"--system must be soul or flao, got '{s}'")
    if delay_frames is not None:
        lists["--delay-frames"] = _numbers(delay_frames, "--delay-frames", DELAY_FRAMES)
    if delay_ms is not None:
        lists["--delay-ms"] = _numbers(delay_ms, "--delay-ms", Range(0.0, DELAY_FRAMES.hi * 1e3 / ANALYSIS_RATE_HZ.lo, "ms"))
    if label is not None:
        lists["--label"] = _values(label, "--label", "names")
        if max(map(len, lists["--label"])) > MAX_LABEL:
            raise InputError(f"--label: a name must be at most {MAX_LABEL} characters long")
    return lists


def _delay(lists: dict, i: int, rate: float) -> float:
    """The loop delay in frames of controller i (InputError beyond ``DELAY_FRAMES``)."""
    if "--delay-frames" in lists:
        return _pick(lists["--delay-frames"], i)
    if "--delay-ms" in lists:
        d, what = _pick(lists["--delay-ms"], i) * 1e-3 * rate, f"--delay-ms {_pick(lists['--delay-ms'], i):g}"
    else:
        system = _pick(lists["--system"], i)
        d, what = DelayModel.from_table(system).frames(rate), f"the {system.upper()} delay model"
    if not DELAY_FRAMES.contains(d):
        raise InputError(
            f"{what} at {rate:g} Hz is {d:.4g} frames: accepted {DELAY_FRAMES.text()} "
            "(the analysis' cost grows with the delay's polynomial degree)"
        )
    return d


def _analyzed(lists: dict, i: int, zeros: tuple, poles: tuple) -> AnalyzedLoop:
    r, c, g = _pick(lists["--rate"], i), _pick(lists["--control"], i), _pick(lists["--gain"], i)
    d = _delay(lists, i, r)
    H, description = _controller(c, g, r, _pick(lists["--forgetting"], i), zeros, poles)
    loop = Loop(H, Plant(d, _pick(lists["--chi"], i)), r)
    name = _pick(lists["--label"], i) if "--label" in lists else f"{c.upper()} {r:g} Hz g={g:g}"
    return AnalyzedLoop(name, c, description, d / r * 1e3, loop, analyze(loop))


# ---------------------------------------------------------------- design


def _render_design(results: list[DesignResult], disturbance: Disturbance, console: Console) -> None:
    roots = Table(title="Roots (H = g ∏(1 − β z⁻¹) / ∏(1 − α z⁻¹)), designed and the paper's", title_justify="left", box=box.SIMPLE_HEAD)
    for name in ("rate", "", "zeros β", "poles α"):
        roots.add_column(name, justify="right" if name == "rate" else "left")
    perf = Table(
        title=f"Performance under the design cost, |1 + HP| > ε = {results[0].epsilon:g} "
        "(the paper's filter and the integrator at their best gains)",
        title_justify="left",
        box=box.SIMPLE_HEAD,
    )
    for name in ("rate", "", "gain", "GM", "PM", "min|1+L|", "|S(13)|", "|T(127)|", "jitter"):
        perf.add_column(name, justify="left" if name == "" else "right")
    for r in results:
        rows = [("designed", r.iir, ""), ("in use", r.in_use, "dim"), ("paper", r.table, "dim"), ("integrator", r.integrator, "dim")]
        for name, c, style in rows:
            if c is None:
                continue
            a = c.analysis
            first = f"{r.rate_hz:g}" if name == "designed" else ""
            if name != "integrator":
                roots.add_row(
                    first,
                    name,
                    " ".join(f"{z.real:+.3f}" for z in c.filter.zeros),
                    " ".join(f"{p.real:+.3f}" for p in c.filter.poles),
                    style=style,
                )
            perf.add_row(
                first,
                name,
                f"{c.filter.gain:.3f}",
                _fmt(a.gain_margin, ".2f"),
                _fmt(a.phase_margin_deg, ".0f") + "°",
                f"{a.modulus_margin:.3f}",
                f"{a.rejection_13hz:.3f}",
                _fmt(a.noise_127hz, ".3f"),
                f"{c.jitter_mas:.2f}",
                style=style,
            )
    console.print(roots)
    console.print(perf)
    for r in results:
        console.print(
            f"{r.rate_hz:g} Hz: the designed filter rejects the 13 Hz line {r.rejection_ratio:.2f}x better than "
            f"the integrator; delay {r.delay_frames:.2f} frames; designed in {r.runtime_s:.1f} s"
        )
    turb = disturbance.turbulence
    console.print(
        f"jitter: residual Tip/Tilt RMS per axis (mas). Disturbance: von Kármán Tip/Tilt, seeing "
        f'{figure_text(turb.seeing_arcsec)}", L0 {figure_text(turb.outer_scale_m)} m, wind {figure_text(turb.wind_speed_m_s)} m/s; '
        f"vibrations: {disturbance.vibrations.source}; noise {figure_text(disturbance.noise_mas)} mas/frame; "
        f"{disturbance.resonance_mas:g} mas line at {disturbance.resonance_hz:g} Hz weighted by |T|².",
        style="dim",
    )


@dataclass(frozen=True)
class DesignOptions:
    """The options of `filter design` (an option table: see ``option_table``)."""

    rate: str = typer.Option(
        "1700,1350,1000,750",
        "--rate",
        metavar="HZ[,HZ…]",
        help=f"Frame rate(s) in Hz ({DESIGN_RATE_HZ.text()}, at most {MAX_DESIGN_RATES}); default the paper's four.",
    )
    epsilon: float = typer.Option(0.2, "--epsilon", parser=number(EPSILON), help="Modulus margin: |1 + H P| > ε on the band, 0 < ε < 1.")
    seeing: float = seeing_option(defaults.SEEING_ARCSEC)
    wind: float = wind_option(defaults.WIND_M_S)
    outer_scale: float = outer_scale_option(defaults.L0_M)
    vibrations: Path | None = typer.Option(
        None,
        "--vibrations",
        metavar="FILE|NAME",
        help="Vibration lines (TOML as tables/lbt_vibrations.toml), or a profile: lbt (default), lbt-onsky.",
    )
    noise: float = typer.Option(
        Disturbance.noise_mas,
        "--noise",
        parser=number(NOISE_MAS),
        metavar="MAS",
        help=f"White measurement noise, RMS per frame and axis ({NOISE_MAS.text()}).",
    )
    resonance_line: float = typer.Option(
        Disturbance.resonance_mas,
        "--resonance-line",
        parser=number(NOISE_MAS),
        metavar="MAS",
        help=f"RMS of the 127 Hz line that keeps |T(127 Hz)| low ({NOISE_MAS.text()}).",
    )
    delay_ms: float | None = typer.Option(
        None,
        "--delay-ms",
        parser=number(Range(0.0, math.inf, "ms")),
        help=f"Loop delay in ms for all rates (default: SOUL's delay model; at most {DESIGN_DELAY_FRAMES.hi:g} frames).",
    )
    seed: int = typer.Option(
        defaults.SEED, "--seed", parser=number(SEED), help=f"Seed of the differential-evolution search ({SEED.text()})."
    )
    plant: Path | None = typer.Option(
        None,
        "--plant",
        metavar="PLANT.toml",
        help="Identified plant ('telemetry identify --out'): its rate, delay, seeing, L0, vibrations and Tip/Tilt noise "
        "replace --rate, --delay-ms, --seeing, --L0, --vibrations and --noise.",
    )
    out: Path | None = typer.Option(None, "--out", metavar="FILE.csv", help="Write the designed roots table (for 'configure --roots').")
    json_output: bool = JSON_OUTPUT
    plot: Path | None = typer.Option(None, "--plot", metavar="FILE.png", help="Write |S|, |T| and Nyquist of the designs.")


@command(DesignOptions)
def design_command(o: DesignOptions) -> int:
    """Design Tip/Tilt IIR filters for given frame rates, beside the best integrator.

    The filters (4 zeros, 4 poles with one at z = 1, and the gain) minimise the residual
    Tip/Tilt variance — temporal error on turbulence and vibrations plus noise propagation —
    under the modulus-margin constraint |1 + H P| > ε, side by side with the best integrator
    under the same constraint and cost.

    Example: soulctl filter design --rate 1700 --out roots.csv --plot design.png
    """
    rates, delays = _design_inputs(o)
    in_use = None
    if o.plant is not None:
        plant = read_plant(o.plant)
        rates, delays = [DESIGN_RATE_HZ.check(plant.rate_hz, f"--plant {o.plant}: rate_hz")], [plant.delay.value]
        disturbance = plant_disturbance(plant, o.wind, o.resonance_line)
        tt = plant.tip_tilt_filter
        in_use = tt.with_gain(tt.gain * float(plant.chi(2)[0])) if tt is not None else None  # the design's plant has chi = 1
    else:
        disturbance = Disturbance(
            turbulence=TurbulenceTipTilt(o.seeing, o.outer_scale, o.wind),
            vibrations=VibrationSpectrum.read(o.vibrations) if o.vibrations is not None else VibrationSpectrum.lbt_default(),
            noise_mas=o.noise,
            resonance_mas=o.resonance_line,
        )
    results = []
    for i, (r, d) in enumerate(zip(rates, delays)):
        with progress.step(f"designing the {r:g} Hz filter ({i + 1} of {len(rates)}, ~5 s each)"):
            results.append(design_tt_filter(r, disturbance, o.epsilon, delay_frames=d, seed=o.seed, in_use=in_use))
    if o.out is not None:
        atomic_write_text(o.out, roots_table_csv(results, _design_header(results, disturbance, o.epsilon, o.delay_ms, o.seed)))
    if o.plot is not None:
        _plot_designs(results, o.epsilon, o.plot)
    if o.json_output:
        print_json({"designs": [x.to_dict() for x in results], "disturbance": _disturbance_dict(disturbance), "seed": o.seed})
    else:
        console = make_console()
        _render_design(results, disturbance, console)
        for path in (o.out, o.plot):
            if path is not None:
                console.print(f"written {path}")
    return 0


def _design_inputs(o: DesignOptions) -> tuple[list[float], list[float | None]]:
    """The rates and their delays in frames (None: SOUL's model), every option checked and the
    outputs checked before any work."""
    rates = _numbers(o.rate, "--rate", DESIGN_RATE_HZ, limit=MAX_DESIGN_RATES)
    if len(set(rates)) != len(rates):
        raise InputError(f"--rate lists a frame rate twice: {o.rate}")
    EPSILON.check(o.epsilon, "--epsilon")
    for value, name, accepted in (
        (o.noise, "--noise", NOISE_MAS),
        (o.resonance_line, "--resonance-line", NOISE_MAS),
        (o.seed, "--seed", SEED),
    ):
        accepted.check(value, name)
    delays = [None if o.delay_ms is None else _design_delay(o.delay_ms, r) for r in rates]
    if o.plant is not None and (o.vibrations is not None or o.delay_ms is not None):
        raise InputError("--plant gives the vibrations and the delay: drop --vibrations/--delay-ms (or --plant)")
    for path, option in ((o.out, "--out"), (o.plot, "--plot")):
        if path is not None:
            check_output_path(path, option, [("--vibrations", o.vibrations), ("--plant", o.plant)])
    if o.out is not None and o.plot is not None and same_file(o.out, o.plot):
        raise InputError(f"--out and --plot name the same file {o.out}")
    if o.plot is not None:
        from ..plots.figure import plot_format

        plot_format(o.plot)
    return rates, delays


def _design_header(results: list, disturbance: Disturbance, epsilon: float, delay_ms: float | None, seed: int) -> str:
    """The roots table's header: what the filters were designed for."""
    turb = disturbance.turbulence
    return (
        f"Tip/Tilt IIR roots designed by soulctl {__version__} (soulctl filter design):\n"
        f"epsilon {epsilon:g}, seeing {figure_text(turb.seeing_arcsec)} arcsec, wind {figure_text(turb.wind_speed_m_s)} m/s, "
        f"L0 {figure_text(turb.outer_scale_m)} m, noise {figure_text(disturbance.noise_mas)} mas/frame, "
        f"{disturbance.resonance_mas:g} mas line "
        f"at {RESONANCE_HZ:g} Hz, seed {seed};\n"
        f"vibrations: {disturbance.vibrations.source};\n"
        f"delay: {'SOUL delay model' if delay_ms is None else f'{delay_ms:g} ms'}.\n"
        "H(z) = g * prod(1 - zero_k z^-1) / prod(1 - pole_l z^-1); gains at design: "
        + ", ".join(f"{x.rate_hz:g} Hz {x.iir.filter.gain:.3f}" for x in results)
    )


def _disturbance_dict(disturbance: Disturbance) -> dict:
    turb = disturbance.turbulence
    return {
        "seeing_arcsec": turb.seeing_arcsec,
        "wind_m_s": turb.wind_speed_m_s,
        "outer_scale_m": turb.outer_scale_m,
        "vibrations": disturbance.vibrations.source,
        "noise_mas": disturbance.noise_mas,
        "resonance_line_mas": disturbance.resonance_mas,
        "resonance_hz": RESONANCE_HZ,
    }


def _plot_designs(results: list, epsilon: float, plot: Path) -> None:
    """The designed IIRs (solid) and the best integrators (dashed), one colour per rate."""
    from ..plots.figure import save_figure
    from ..plots.transfer import Curve, transfer_figure

    colors = ["C0", "C1", "C2", "C3", "C4", "C5", "C6", "C7"]
    curves = []
    for i, x in enumerate(results):
        col = colors[i % len(colors)]
        plant = Plant(x.delay_frames)
        curves.append(Curve(f"IIR {x.rate_hz:g} Hz g={x.iir.filter.gain:.2f}", Loop(x.iir.filter, plant, x.rate_hz), col))
        curves.append(
            Curve(f"INT {x.rate_hz:g} Hz g={x.integrator.filter.gain:.2f}", Loop(x.integrator.filter, plant, x.rate_hz), col, "--")
        )
    title = "Designed Tip/Tilt IIR filters (solid) and the best integrators (dashed)"
    save_figure(transfer_figure(curves, title, epsilon=epsilon), plot)


def _design_delay(delay_ms: float, rate: float) -> float:
    """--delay-ms in frames at ``rate``, within ``DESIGN_DELAY_FRAMES``."""
    if not (math.isfinite(delay_ms) and delay_ms >= 0):
        raise InputError(f"--delay-ms must be a number >= 0 ms, got {delay_ms:.10g}")
    d = delay_ms * 1e-3 * rate
    if not DESIGN_DELAY_FRAMES.contains(d):
        raise InputError(f"--delay-ms {delay_ms:.10g} at {rate:g} Hz is {d:.4g} frames: the design accepts {DESIGN_DELAY_FRAMES.text()}")
    return d


app.command(name="analyze")(analyze_command)
app.command(name="design")(design_command)
