"""|S| and |T| versus frequency and the Nyquist plot of one or more loops, in the style of the
paper's figures comparing SOUL-IIR, SOUL-INT and FLAO-INT (Fig. IIR1700TF, TFcomp)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..control.transfer import RESONANCE_HZ, VIBRATION_HZ, Loop, frequency_grid
from .figure import new_figure

if TYPE_CHECKING:  # matplotlib is imported when a figure is made
    from matplotlib.figure import Figure


@dataclass(frozen=True)
class Curve:
    label: str
    loop: Loop
    color: str | None = None
    linestyle: str = "-"


def transfer_figure(curves: list[Curve], title: str = "", epsilon: float | None = None) -> Figure:
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
