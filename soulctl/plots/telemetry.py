"""The figure of `soulctl telemetry psd`: modal PSDs and the cumulative Tip/Tilt jitter, in the
style of the paper's spectra."""

from __future__ import annotations

from pathlib import Path

from .loop import new_figure
from .transfer import save_figure

LABELS = {"measured_modes": "measured (R s)", "command_modes": "commands (M^-1 c)", "pseudo_open_loop": "pseudo-open loop"}


def write_psd_figure(path: Path, s, title: str) -> None:
    """PSDs of each record and mode (top), cumulative Tip/Tilt jitter per axis (bottom)."""
    fig = new_figure((6.4, 7.2) if s.tt_cumulative_mas else (6.4, 4.4))
    axes = fig.subplots(2 if s.tt_cumulative_mas else 1, 1, sharex=True, squeeze=False)[:, 0]
    f = s.f_hz[1:]
    for i, (name, p) in enumerate(s.psd.items()):
        for j, mode in enumerate(s.modes):
            axes[0].loglog(
                f, p[j, 1:], color=f"C{j}", linestyle=("-", "--", ":")[i % 3], linewidth=1, label=f"{LABELS.get(name, name)}, mode {mode}"
            )
    axes[0].set_ylabel("PSD [nm²/Hz]")
    axes[0].set_title(title, fontsize=9)
    axes[0].legend(fontsize=7)
    if s.tt_cumulative_mas:
        for i, (name, c) in enumerate(s.tt_cumulative_mas.items()):
            axes[1].semilogx(f, c[1:], color=f"C{i}", label=LABELS.get(name, name))
        axes[1].set_ylabel("cumulative Tip/Tilt jitter per axis [mas]")
        axes[1].legend(fontsize=8)
    axes[-1].set_xlabel("frequency [Hz]")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.25)
    save_figure(fig, path)
