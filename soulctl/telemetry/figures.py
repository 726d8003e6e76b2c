"""The Tip/Tilt figures of a closed loop, one definition each, computed from the series the
telemetry model holds.  `loop run` (its table, ``--json`` and ``jitter.png``) and `telemetry
psd` on the run's record call these functions on the same series over the same window, so
that one run reports one number everywhere.

Rules in force:

* **Window**: the frames after the ones left out while the loop closes (a run's
  ``skipped_frames``; 0 for another system's record), up to a divergence.
* **Jitter** (per axis, mas): the square root of the Welch PSD of each axis (Hann window,
  mean removed per segment), averaged over the two axes and integrated from a frequency to
  Nyquist.  The segment is the window, at most the power of two that gives a resolution of
  ``RESOLUTION_HZ`` or finer; the resolution is stated with the figure.  "All", from 0 Hz,
  is the window's RMS (mean removed, the two axes' variances averaged): the power below the
  resolution is counted in the first bin (where a short window's Hann weighting puts more
  than the window's variance in the other bins, the PSD is scaled to it).  "Above 3 Hz" integrates from the first bin at or
  above ``JITTER_EDGE_HZ`` and is n/a when the resolution is coarser than that edge.  This
  is the paper's cumulative Tip/Tilt jitter figure read at its two ends.
* **Rejection at f** (13 Hz, the LBT line): |residual / pseudo-open loop| from their PSDs in
  the bins within max(1 Hz, one bin) of f; n/a when the resolution is coarser than
  ``REJECTION_RESOLUTION_HZ`` or when the pseudo-open loop holds no line there: its PSD in
  those bins is less than ``LINE_CONTRAST`` times the median of its neighbours within
  ``NEIGHBOURHOOD_HZ`` (a ratio of two continua says nothing of a line's rejection).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..control.delay import fractional_taps

RESOLUTION_HZ = 1.0  # the spectra's resolution where the window allows
JITTER_EDGE_HZ = 3.0  # the paper's jitter "above 3 Hz" (it quotes 3-425 Hz)
MIN_JITTER_FRAMES = 4  # a spectrum needs a few frames
REJECTION_RESOLUTION_HZ = 5.0  # a rejection at 13 Hz needs bins this fine or finer
LINE_CONTRAST = 3.0  # a line stands this far above its neighbours' median PSD
NEIGHBOURHOOD_HZ = 10.0  # the neighbours of a line: within this distance, outside its bins


def pseudo_open_loop(measured: np.ndarray, command_modes: np.ndarray, delay_frames: float, structure_ba=None) -> np.ndarray:
    """Pseudo-open-loop modes from telemetry: m_pol(k) = m(k) + (mirror modes during frame k),
    the mirror holding the commands delayed by d = n + e frames,
    (1 - e) c(k - n) + e c(k - n - 1) (the delay line's own rule).  Rows are frames; the first
    n + 1 rows use commands from before the record (taken as zero).

    ``structure_ba``: the structural resonance G(z) = b/a on Tip/Tilt (``control.structure``),
    whose wavefront Tip/Tilt adds G u to the mirror's u: the plant is z^-d (1 + G), and so is
    the term added to Tip/Tilt (started at rest with the record; it rings down in ~3/(zeta w0),
    25 ms at 127 Hz)."""
    from scipy.signal import lfilter

    n, e = fractional_taps(delay_frames)
    c = np.asarray(command_modes, dtype=float)
    shifted = np.zeros_like(c)
    shifted[n:] += (1 - e) * c[: len(c) - n]
    if e:
        shifted[n + 1 :] += e * c[: len(c) - n - 1]
    if structure_ba is not None:
        b, a = structure_ba
        shifted[:, :2] += lfilter(b, a, shifted[:, :2], axis=0)
    return np.asarray(measured, dtype=float) + shifted


# The records a figure is computed from, as every output names them.
RECORD_LABELS = {
    "measured_modes": "measured (R s)",
    "command_modes": "commands (M^-1 c)",
    "residual_modes": "residual (true wavefront)",
    "pseudo_open_loop": "pseudo-open loop",
}


def mas_text(value: float | None) -> str:
    """A jitter as every output prints it (mas, two decimals; n/a when not available)."""
    return "n/a" if value is None else f"{value:.2f}"


def welch_segment(frames: int, rate_hz: float) -> int:
    """Frames per Welch segment: the window, at most the power of two that resolves RESOLUTION_HZ."""
    return int(min(frames, 2 ** math.ceil(math.log2(rate_hz / RESOLUTION_HZ))))


def _psd(x: np.ndarray, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    from scipy.signal import welch

    return welch(x, fs=rate_hz, window="hann", nperseg=welch_segment(len(x), rate_hz), detrend="constant", axis=0)


@dataclass(frozen=True)
class Jitter:
    """The cumulative Tip/Tilt jitter of a window: per axis (mas), from each frequency to Nyquist."""

    f_hz: np.ndarray
    cumulative_mas: np.ndarray
    frames: int  # the window's

    @property
    def resolution_hz(self) -> float:
        return float(self.f_hz[1] - self.f_hz[0])

    @property
    def total(self) -> float:
        """The jitter over the whole band (from 0 Hz)."""
        return float(self.cumulative_mas[0])

    def above(self, edge_hz: float = JITTER_EDGE_HZ) -> float | None:
        """The jitter from the first bin at or above ``edge_hz``; None when the resolution is
        coarser than the edge."""
        if self.resolution_hz > edge_hz:
            return None
        return float(self.cumulative_mas[int(np.searchsorted(self.f_hz, edge_hz))])


def tip_tilt_jitter(tip_tilt_nm: np.ndarray, rate_hz: float, nm_per_mas: float) -> Jitter | None:
    """The jitter of a window of Tip/Tilt ((frames, 2), nm RMS of the unit-RMS modes); None
    for fewer than MIN_JITTER_FRAMES frames."""
    x = np.asarray(tip_tilt_nm, dtype=float)
    if len(x) < MIN_JITTER_FRAMES:
        return None
    f, p = _psd(x, rate_hz)
    df = f[1] - f[0]
    per_axis = p.mean(axis=1)
    variance = float(np.mean(x.var(axis=0)))
    above_first = float(per_axis[1:].sum() * df)
    if variance >= above_first:  # what lies below the resolution goes to the first bin (Parseval)
        per_axis[0] = (variance - above_first) / df
    else:  # a short window's Hann weighting made more than the window holds: scaled to it
        per_axis *= variance / float(per_axis.sum() * df)
    cumulative = np.sqrt(np.cumsum(per_axis[::-1])[::-1] * df)
    return Jitter(f, cumulative / nm_per_mas, len(x))


def rejection(residual: np.ndarray, pseudo_open: np.ndarray, rate_hz: float, f_hz: float) -> tuple[float | None, str | None]:
    """(|residual / pseudo-open loop| at ``f_hz``, None) from the windows' Welch PSDs (mean of
    the columns), or (None, why it is not available)."""
    if len(residual) < MIN_JITTER_FRAMES:
        return None, "run too short"
    f, pr = _psd(np.asarray(residual, dtype=float), rate_hz)
    _, pp = _psd(np.asarray(pseudo_open, dtype=float), rate_hz)
    pr, pp = pr.reshape(len(f), -1).mean(axis=1), pp.reshape(len(f), -1).mean(axis=1)
    df = f[1] - f[0]
    if df > REJECTION_RESOLUTION_HZ:
        return None, f"run too short: {df:.3g} Hz bins (needs {REJECTION_RESOLUTION_HZ:g} Hz or finer)"
    band = np.abs(f - f_hz) <= max(1.0, df)
    around = (np.abs(f - f_hz) <= NEIGHBOURHOOD_HZ) & ~band & (f > 0)
    contrast = float(pp[band].mean() / np.median(pp[around])) if around.any() and np.median(pp[around]) > 0 else math.inf
    if contrast < LINE_CONTRAST:
        return None, f"no line at {f_hz:g} Hz to reject (pseudo-open loop {contrast:.2g}x its neighbours)"
    return float(np.sqrt(pr[band].sum() / pp[band].sum())), None
