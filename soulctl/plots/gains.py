"""Figures of a gain optimisation, as the paper's: the optimised gain per mode (MGM against
trial-and-error, Fig. GAINday/GAINnight) and the time series of a few modal gains, the
estimated optical gain and the Strehl ratio (Fig. timeSerie)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .figure import new_figure, save_figure

if TYPE_CHECKING:
    from matplotlib.figure import Figure

TIME_SERIES_MODES = (1, 2, 10, 50, 200)  # 1-based, as in the paper's figure (no. 1 is Tip)
LABELS = {"mgm": "MGM", "trial": "trial-and-error"}
COLOURS = {"mgm": "k", "trial": "C3"}  # the paper: black MGM, red trial-and-error


def gain_vector_figure(gains: dict[str, np.ndarray], title: str) -> Figure:
    """Gain per mode, one line per method."""
    fig = new_figure()
    ax = fig.subplots()
    for method, g in gains.items():
        ax.plot(np.arange(1, len(g) + 1), g, color=COLOURS.get(method), label=LABELS.get(method, method), linewidth=1)
    ax.set_xscale("log")
    ax.set_xlabel("mode")
    ax.set_ylabel("gain")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=9)
    return fig


def time_series_figure(result, title: str) -> Figure:
    """Three panels against simulated time: gains of TIME_SERIES_MODES (steps at each change),
    the slope sensitivity k and 1 / optical gain estimate of OGTL, the phases and their Strehl
    ratios (the table's "during the run")."""
    tm = result.loop.telemetry
    rate = tm.rate_hz
    end = result.loop.frame / rate
    fig = new_figure((6.4, 7.2))
    ax_g, ax_k, ax_s = fig.subplots(3, 1, sharex=True)
    frames, gains = tm.gain_arrays()
    t = np.append(frames / rate, end)
    for mode in TIME_SERIES_MODES:
        if mode <= gains.shape[1]:
            ax_g.step(t, np.append(gains[:, mode - 1], gains[-1, mode - 1]), where="post", label=f"mode {mode}", linewidth=1)
    ax_g.set_ylabel("gain")
    k = np.asarray(tm.sensitivity)
    ax_k.plot(np.arange(len(k)) / rate, k, color="C0", label="slope sensitivity k")
    ogtl = tm.aux_arrays("ogtl")
    if len(ogtl.get("frame", [])):
        ax_k.plot(ogtl["frame"] / rate, 1.0 / np.maximum(ogtl["optical_gain"], 1e-3), ".", color="C1", label="1 / optical gain estimate")
    ax_k.set_ylabel("k")
    _phase_strehls(ax_s, result, rate)
    ax_s.set_ylabel(f"Strehl ({result.request.run.band})")
    ax_s.set_xlabel("time [s]")
    for ax in (ax_g, ax_k, ax_s):
        ax.grid(True, alpha=0.25)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8, ncol=3 if ax is ax_g else 1)
    ax_g.set_title(title, fontsize=10)
    return fig


def _phase_strehls(ax, result, rate: float) -> None:
    """The run's phases shaded, and the Strehl ratio of its *before* and *after* phases drawn
    over them at the table's value ("during the run"), labelled with it as the table prints it:
    one number per figure (the live controlled-mode estimate, blind to fitting error and
    biased by noise at faint stars, is not drawn)."""
    for name, (a, b) in result.phases.items():
        ax.axvspan(a / rate, b / rate, alpha=0.08, color={"before": "C0", "optimisation": "C1", "after": "C2"}.get(name, "0.5"))
        phase = result.during_run.get(name)
        if phase is not None:
            ax.hlines(phase.strehl, a / rate, b / rate, color="C2" if name == "after" else "C0", label=f"{name}: {phase.strehl:.3f}")


def gain_figure_names(methods) -> tuple[str, ...]:
    """The files ``write_gain_figures`` writes for these methods."""
    methods = list(methods)
    return ("gains.png", *("timeseries.png" if len(methods) == 1 else f"timeseries_{m}.png" for m in methods))


def write_gain_figures(directory: Path, results: dict) -> list[Path]:
    """gains.png (all methods) and timeseries[_METHOD].png per method, written atomically."""
    first = next(iter(results.values()))
    rr = first.request.run
    obs = rr.observation
    label = f'R = {obs.magnitude_r:g}, {obs.frame_rate_hz:g} Hz, seeing {rr.seeing_arcsec:g}"'
    names = gain_figure_names(results)
    figures = [(names[0], gain_vector_figure({m: x.gains for m, x in results.items()}, f"Optimised gains, {label}"))]
    for name, (method, result) in zip(names[1:], results.items()):
        figures.append((name, time_series_figure(result, f"{LABELS.get(method, method)}: {label}")))
    out = []
    for name, fig in figures:
        save_figure(fig, directory / name)
        out.append(directory / name)
    return out
