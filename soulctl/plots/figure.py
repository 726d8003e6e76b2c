"""The figures' common helpers: a figure on the Agg canvas (no pyplot state) and its atomic
writer, with the formats a --plot path may name."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import InputError
from ..files import atomic_write

if TYPE_CHECKING:  # matplotlib is imported when a figure is made
    from matplotlib.figure import Figure
    from matplotlib.text import Text

FORMATS = ("png", "pdf", "svg")


def plot_format(path: Path) -> str:
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in FORMATS:
        raise InputError(f"--plot must end in .png, .pdf or .svg, got '{path.name}'")
    return fmt


def new_figure(size=(6.4, 4.8)) -> Figure:
    """A constrained-layout figure on the Agg canvas (no pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
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
