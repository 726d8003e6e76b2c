"""The figure of `soulctl telemetry psd`: modal PSDs and the cumulative Tip/Tilt jitter, in the
style of the paper's spectra."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..control.mgm import unit_open_loops
from ..telemetry.figures import RECORD_LABELS
from .figure import new_figure, save_figure
from .loop import draw_jitter

LABELS = RECORD_LABELS


def write_psd_figure(path: Path, s, title: str) -> None:
    """PSDs of each record and mode (top), cumulative Tip/Tilt jitter per axis (bottom)."""
    fig = new_figure((6.4, 7.2) if s.jitter else (6.4, 4.4))
    axes = fig.subplots(2 if s.jitter else 1, 1, sharex=True, squeeze=False)[:, 0]
    f = s.f_hz[1:]
    for i, (name, p) in enumerate(s.psd.items()):
        for j, mode in enumerate(s.modes):
            axes[0].loglog(
                f, p[j, 1:], color=f"C{j}", linestyle=("-", "--", ":")[i % 3], linewidth=1, label=f"{LABELS.get(name, name)}, mode {mode}"
            )
    axes[0].set_ylabel("PSD [nm²/Hz]")
    axes[0].set_title(title, fontsize=9)
    axes[0].legend(fontsize=7)
    axes[-1].set_xlabel("frequency [Hz]")
    if s.jitter:
        draw_jitter(axes[1], s.jitter, LABELS)
    for ax in axes:
        ax.grid(True, which="both", alpha=0.25)
    save_figure(fig, path)


IDENTIFY_FIGURES = ("identify_rejection.png", "identify_vibrations.png", "identify_variance.png")


def write_identify_figures(directory: Path, ident) -> list[Path]:
    """The fits of `telemetry identify` against the data: a measured-mode PSD per optical-gain
    group with sigma^2 |S|^2 at the identified delay and chi, the pseudo-open-loop Tip/Tilt PSD
    with the lines found, the modal variances with the von Karman fit."""
    out: list[Path] = []
    rec, rej, plant = ident.record, ident.rejection, ident.plant
    fig = new_figure((6.4, 4.4))
    ax = fig.subplots()
    chi = plant.chi(rec.n_modes)
    for j, (lo, hi) in enumerate(rej.groups):
        mode = (lo + hi) // 2 - 1
        L = rec.gains[mode] * unit_open_loops([rec.filters[mode]], [1.0], plant.delay.value, rec.rate_hz, rec.f_hz[1:])[0]
        model = rej.noise_nm2[mode] * 2 / rec.rate_hz / np.abs(1 + chi[mode] * rec.sensitivity * L) ** 2
        ax.loglog(rec.f_hz[1:], rec.p_m[mode, 1:], color=f"C{j}", linewidth=0.8, label=f"mode {mode + 1} (m/k)")
        ax.loglog(rec.f_hz[1:], model, color=f"C{j}", linestyle="--", linewidth=1.2)
    ax.axvline(rej.f_low_hz, color="k", linewidth=0.6, linestyle=":")
    ax.set_title(f"noise rejection fit (dashed): d = {plant.delay.value:.3f} frames; fitted above {rej.f_low_hz:.0f} Hz", fontsize=9)
    _finish(ax, fig, "PSD [nm²/Hz]", "frequency [Hz]", directory / IDENTIFY_FIGURES[0], out)
    fig = new_figure((6.4, 4.4))
    ax = fig.subplots()
    f, p = ident.line_psd
    ax.loglog(f[1:], p[1:], linewidth=0.8, label="pseudo-open-loop Tip/Tilt (mean of the axes)")
    for line in ident.lines:
        ax.axvline(line.frequency.value, color="C3", linewidth=0.6, alpha=0.6)
    ax.set_title(f"{len(ident.lines)} vibration lines found", fontsize=9)
    _finish(ax, fig, "PSD [mas²/Hz]", "frequency [Hz]", directory / IDENTIFY_FIGURES[1], out)
    fig = new_figure((6.4, 4.4))
    ax = fig.subplots()
    modes = np.arange(1, rec.n_modes + 1)
    ax.loglog(modes, np.maximum(ident.pol_variance_nm2, 1e-3), ".", markersize=3, label="pseudo-open loop less noise")
    if ident.model_variance_nm2 is not None and plant.turbulence is not None:
        t = plant.turbulence
        L0 = "L0 not estimated" if "L0" in ident.not_estimated else f"L0 {t.L0_m:g} m"
        ax.loglog(modes, ident.model_variance_nm2, "-", label=f'von Kármán: seeing {t.seeing_arcsec:.3f}", {L0}')
    _finish(ax, fig, "modal variance [nm²]", "mode", directory / IDENTIFY_FIGURES[2], out)
    return out


def _finish(ax, fig, ylabel: str, xlabel: str, path: Path, out: list) -> None:
    ax.set_ylabel(ylabel)
    ax.set_xlabel(xlabel)
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=7)
    save_figure(fig, path)
    out.append(path)
