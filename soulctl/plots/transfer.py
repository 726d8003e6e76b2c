"""|S| and |T| versus frequency and the Nyquist plot of one or more loops, in the style of the
paper's figures comparing SOUL-IIR, SOUL-INT and FLAO-INT (Fig. IIR1700TF, TFcomp)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..control.transfer import RESONANCE_HZ, VIBRATION_HZ, Loop, frequency_grid
from ..errors import InputError
from ..files import atomic_write

if TYPE_CHECKING:  # matplotlib is imported when a figure is made
    from matplotlib.figure import Figure
    from matplotlib.text import Text

FORMATS = ("png", "pdf", "svg")


@dataclass(frozen=True)
class Curve:
    label: str
    loop: Loop
    color: str | None = None
    linestyle: str = "-"


def plot_format(path: Path) -> str:
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in FORMATS:
        raise InputError(f"--plot must end in .png, .pdf or .svg, got '{path.name}'")
    return fmt


def transfer_figure(curves: list[Curve], title: str = "", epsilon: float | None = None) -> Figure:
    from .loop import new_figure

    fig = new_figure((14, 4.6))
    ax_s, ax_t, ax_n = fig.subplots(1, 3, gridspec_kw={"width_ratios": [1.15, 1.15, 0.9]})
    f_lo = 1.0
    for i, c in enumerate(curves):
        f = frequency_grid(c.loop.rate_hz, 2000)
        f = f[f >= f_lo]
        style = {"color": c.color or f"C{i % 10}", "linestyle": c.linestyle, "linewidth": 1.4}
        ax_s.loglog(f, np.abs(c.loop.sensitivity(f)), label=c.label, **style)
        ax_t.loglog(f, np.abs(c.loop.complementary(f)), label=c.label, **style)
        L = c.loop.open_loop(frequency_grid(c.loop.rate_hz, 3000))
        ax_n.plot(L.real, L.imag, **style)
        ax_n.plot(L.real, -L.imag, alpha=0.35, **{**style, "linewidth": 0.8})
    for ax, name in ((ax_s, "Sensitivity |S| (rejection)"), (ax_t, "Complementary sensitivity |T| (noise transfer)")):
        for fx, text in ((VIBRATION_HZ, "13 Hz"), (RESONANCE_HZ, "127 Hz")):
            ax.axvline(fx, color="0.5", linestyle=":", linewidth=1)
            ax.annotate(
                text, (fx, 1.0), xycoords=("data", "axes fraction"), xytext=(3, -12), textcoords="offset points", fontsize=8, color="0.35"
            )
        ax.axhline(1.0, color="0.75", linewidth=0.8)
        ax.axhline(1 / np.sqrt(2), color="0.75", linewidth=0.8, linestyle="--")
        ax.set_xlabel("frequency [Hz]")
        ax.set_ylabel("amplitude")
        ax.set_title(name, fontsize=10)
        ax.grid(True, which="both", alpha=0.25)
    ax_s.legend(fontsize=8, loc="lower right")
    # Nyquist plot around -1, with the epsilon circle of the design constraint.
    ax_n.plot([-1], [0], "r+", markersize=10)
    theta = np.linspace(0, 2 * np.pi, 200)
    if epsilon:
        ax_n.plot(-1 + epsilon * np.cos(theta), epsilon * np.sin(theta), "r:", linewidth=1, label=f"|1+L| = {epsilon:g}")
        ax_n.legend(fontsize=8, loc="lower left")
    ax_n.plot(np.cos(theta), np.sin(theta), color="0.8", linewidth=0.8)
    ax_n.set_xlim(-2.5, 1.0)
    ax_n.set_ylim(-2.0, 2.0)
    ax_n.set_aspect("equal")
    ax_n.set_xlabel("Re L")
    ax_n.set_ylabel("Im L")
    ax_n.set_title("Nyquist plot of L = H P", fontsize=10)
    ax_n.grid(True, alpha=0.25)
    if title:
        fig.suptitle(title, fontsize=11)
    return fig


def _tick_labels(ax) -> list[Text]:
    out = []
    for axis in (ax.xaxis, ax.yaxis):
        for tick in axis.get_major_ticks() + axis.get_minor_ticks():
            out += [tick.label1, tick.label2]
    return out


def save_figure(fig: Figure, path: Path) -> None:
    """Write the figure atomically in the format its suffix names.  Every text is drawn as
    given: '$' in a user's label is a dollar sign, not matplotlib's math mode."""
    fmt = plot_format(path)
    ticks = {id(t) for ax in fig.axes for t in _tick_labels(ax)}  # the formatters' own text: 10^k on log axes is math
    from matplotlib.text import Text

    for text in fig.findobj(Text):
        if id(text) not in ticks:
            text.set_parse_math(False)
    atomic_write(path, lambda tmp: fig.savefig(tmp, format=fmt, dpi=120))
