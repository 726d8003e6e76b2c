"""Figures of a closed-loop run, in the style of the paper's: the long-exposure PSF, the
cumulative Tip/Tilt jitter (residual against pseudo-open loop) and the modal residual
variance."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..control.transfer import VIBRATION_HZ
from ..loop.metrics import band_wavelength
from ..optics.pupil import LBT_DIAMETER_M
from ..telemetry.figures import RECORD_LABELS, mas_text
from .figure import new_figure, save_figure

if TYPE_CHECKING:  # matplotlib is imported when a figure is made: every command would pay ~0.3 s
    from matplotlib.figure import Figure


def psf_figure(psf: np.ndarray, band: str, strehl: float, lambda_over_d_mas: float, pad: int = 2) -> Figure:
    """The PSF (peak = Strehl), log scale, +-20 lambda/D, axes in mas."""
    fig = new_figure((5.6, 4.8))
    ax = fig.subplots()
    n = psf.shape[0]
    half = min(n // 2, 20 * pad)
    crop = psf[n // 2 - half : n // 2 + half, n // 2 - half : n // 2 + half]
    extent = (-half * lambda_over_d_mas / pad, half * lambda_over_d_mas / pad) * 2
    from matplotlib.colors import LogNorm

    im = ax.imshow(np.maximum(crop, 1e-5), norm=LogNorm(vmin=1e-5, vmax=1.0), origin="lower", extent=extent, cmap="inferno")
    fig.colorbar(im, ax=ax, label="intensity / diffraction-limited peak")
    ax.set_xlabel("x [mas]")
    ax.set_ylabel("y [mas]")
    ax.set_title(f"Long-exposure PSF, {band} band: SR = {strehl:.2f}", fontsize=10)
    return fig


def draw_jitter(ax, jitters: dict, labels: dict) -> None:
    """Cumulative Tip/Tilt jitter per axis from each frequency to Nyquist (paper, Fig. of the
    on-sky IIR tests), one curve per ``telemetry.figures.Jitter``; the legend gives each
    curve's whole-band figure, as the tables print it."""
    for i, (name, j) in enumerate(jitters.items()):
        color = "0.35" if name == "pseudo_open_loop" else f"C{(i + 3) % 10}"
        ax.semilogx(j.f_hz[1:], j.cumulative_mas[1:], color=color, label=f"{labels.get(name, name)}: {mas_text(j.total)} mas")
    resolution = next(iter(jitters.values())).resolution_hz
    ax.set_ylabel("cumulative Tip/Tilt jitter per axis [mas]")
    ax.set_xlabel(f"frequency [Hz] ({resolution:.3g} Hz bins; legend: from 0 Hz)")
    ax.legend(fontsize=8)


def jitter_figure(jitters: dict, title: str) -> Figure:
    """``draw_jitter`` of a run's residual and pseudo-open loop, the 13 Hz line marked."""
    fig = new_figure()
    ax = fig.subplots()
    draw_jitter(ax, jitters, RECORD_LABELS)
    ax.axvline(VIBRATION_HZ, color="0.6", linestyle=":", linewidth=1)
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.25)
    return fig


def modal_variance_figure(variance_nm2: np.ndarray, title: str) -> Figure:
    fig = new_figure()
    ax = fig.subplots()
    modes = np.arange(1, len(variance_nm2) + 1)
    ax.loglog(modes, variance_nm2, ".", markersize=3, color="C0")
    ax.set_xlabel("mode")
    ax.set_ylabel("residual variance [nm²]")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.25)
    return fig


LOOP_FIGURES = ("psf.png", "jitter.png", "modal_variance.png")


def write_loop_figures(directory: Path, result) -> list[Path]:
    """``LOOP_FIGURES`` in ``directory`` (atomically; the jitter spectra only when the run
    gives them); the paths."""
    r = result.request
    m = result.metrics
    lod_mas = band_wavelength(r.band) / LBT_DIAMETER_M * 180 / np.pi * 3600e3
    label = f'R = {r.observation.magnitude_r:g}, {r.observation.frame_rate_hz:g} Hz, seeing {r.seeing_arcsec:g}"'
    out = []
    figures = [("modal_variance.png", modal_variance_figure(result.spectra["modal_variance_nm2"], f"Modal residual variance, {label}"))]
    if m.strehl is not None:
        figures.append(("psf.png", psf_figure(result.psf, r.band, m.strehl, lod_mas)))
    if "residual" in result.spectra:
        jitters = {"pseudo_open_loop": result.spectra["pseudo_open_loop"], "residual_modes": result.spectra["residual"]}
        figures.append(("jitter.png", jitter_figure(jitters, f"Tip/Tilt jitter, {label}")))
    for name, fig in figures:
        path = directory / name
        save_figure(fig, path)
        out.append(path)
    return out
