"""Tip/Tilt vibration lines from the pseudo-open-loop PSD (the elab_lib ``vib_est`` idea:
peaks above the turbulence's smooth spectrum, each a damped oscillator).

1. Welch PSD of the pseudo-open-loop Tip and Tilt (mas), segments of up to ``SEGMENT_S``
   (0.125 Hz resolution: a 13 Hz line of damping 0.02 is 0.5 Hz wide at half maximum).
2. The baseline, a running median of the mean PSD over +-``BASELINE_HZ``, computed again
   without the bins of the lines a first pass found (out to ``MASK_WIDTHS`` x zeta f0 of each,
   whose wings would raise it); candidates are local
   maxima between ``F_MIN_HZ`` and 0.45 x the frame rate above the threshold a Welch PSD of
   that many segments exceeds by chance ``FALSE_ALARMS`` times per spectrum (chi-squared with
   2 x segments degrees of freedom per axis: 11 x the baseline for one segment, 2.2 for 30).
3. Each candidate is fitted with the oscillator PSD of ``disturbance.vibrations`` (frequency,
   damping, variance) on top of the baseline, by least squares on the log PSD over the peak.
4. Per axis, the line's variance is the PSD in excess of the baseline over the peak, divided
   by the share of the fitted line's power inside that band.  Lines under ``MIN_RMS_MAS`` on
   both axes are dropped.

Uncertainties: the frequency's from the fit's covariance; the RMS's from the periodogram's
scatter, 1/sqrt(segments x bins in the band).  A line of a short record has few segments
(a 10 s record has one 8 s segment): its RMS is uncertain and the realised RMS of a short
record scatters around the line's nominal RMS (docs/physics.md gives how long a record
must be).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import median_filter
from scipy.optimize import least_squares
from scipy.stats import chi2

from ..disturbance.vibrations import VibrationLine
from .plant import Estimate

SEGMENT_S = 8.0
BASELINE_HZ = 4.0
FALSE_ALARMS = 0.05  # expected false detections per spectrum (sets the threshold)
MAX_DAMPING = 0.1
F_MIN_HZ = 3.0
MIN_RMS_MAS = 1.0
PEAK_HALF_WIDTH_HZ = 2.0  # at least; and 8 x the fitted half width, at most MAX_BAND_HZ
MAX_BAND_HZ = 10.0
MAX_LINES = 12  # candidates fitted, strongest first (a comb of spurious peaks must not cost minutes)
MASK_WIDTHS = 5.0  # a line's bins out of the baseline out to 5 zeta f0 (its PSD at 4 % of the peak)


@dataclass(frozen=True)
class LineEstimate:
    frequency: Estimate
    damping: float
    tip: Estimate  # mas RMS
    tilt: Estimate

    def line(self) -> VibrationLine:
        f, tip, tilt = self.frequency, self.tip, self.tilt
        note = f"identified: {f.value:.2f} +- {f.sigma:.2f} Hz, tip {tip.value:.2f} +- {tip.sigma:.2f}"
        note += f", tilt {tilt.value:.2f} +- {tilt.sigma:.2f} mas"
        damping = float(np.clip(self.damping, 1e-4, 0.9))
        return VibrationLine(self.frequency.value, damping, max(self.tip.value, 0.0), max(self.tilt.value, 0.0), note)


def _oscillator(f: np.ndarray, f0: float, zeta: float) -> np.ndarray:
    """Unit-variance oscillator PSD (``VibrationLine.psd`` with sigma = 1)."""
    w, w0 = 2 * np.pi * f, 2 * np.pi * f0
    return (8 * zeta / w0) * w0**4 / ((w0**2 - w**2) ** 2 + (2 * zeta * w0 * w) ** 2)


def _fit_peak(f: np.ndarray, p: np.ndarray, base: np.ndarray, i: int) -> tuple[float, float, float]:
    """(f0, zeta, f0 sigma) of the oscillator on top of ``base`` near bin i."""
    df = f[1] - f[0]
    band = np.abs(f - f[i]) <= max(PEAK_HALF_WIDTH_HZ, 3 * df)
    fb, pb, bb = f[band], p[band], base[band]
    var0 = max(float(np.sum(pb - bb) * df), 1e-12)

    def resid(x: np.ndarray) -> np.ndarray:
        f0, lz, lv = x
        return np.log(bb + np.exp(lv) * _oscillator(fb, f0, math.exp(lz))) - np.log(pb)

    x0 = [f[i], math.log(max(df / f[i], 0.003)), math.log(var0)]
    lo, hi = [f[i] - 2 * df, math.log(1e-4), math.log(var0) - 5], [f[i] + 2 * df, math.log(MAX_DAMPING), math.log(var0) + 5]
    res = least_squares(resid, x0, bounds=(lo, hi))
    f0, zeta = res.x[0], math.exp(res.x[1])
    try:
        cov = np.linalg.inv(res.jac.T @ res.jac) * np.sum(res.fun**2) / max(1, len(fb) - 3)
        sf = float(math.sqrt(max(cov[0, 0], 0.0)))
    except np.linalg.LinAlgError:
        sf = math.inf
    return f0, zeta, sf


def _axis_variance(f: np.ndarray, p_axis: np.ndarray, base_axis: np.ndarray, f0: float, zeta: float, segments: int) -> Estimate:
    df = f[1] - f[0]
    half = min(max(PEAK_HALF_WIDTH_HZ, 8 * zeta * f0), MAX_BAND_HZ)
    band = np.abs(f - f0) <= half
    share = _share(f[band], df, f0, zeta)
    excess = float(np.sum(p_axis[band] - base_axis[band]) * df) / max(share, 1e-6)
    rms = math.sqrt(max(excess, 0.0))
    scatter = float(np.sum(p_axis[band]) * df) / max(share, 1e-6) / math.sqrt(max(1, segments * band.sum()))
    return Estimate(rms, 0.5 * scatter / rms if rms > 0 else math.inf)


def _share(bins: np.ndarray, df: float, f0: float, zeta: float) -> float:
    """The variance of a unit-variance line the Welch bins ``bins`` (each df wide) hold: the
    oscillator's PSD integrated over them on a grid 20 x finer than its width, not sampled at
    the bins (a line narrower than a bin, zeta f0 < df, sampled there is missed or counted
    many times over: a sinusoid's RMS came out 3.6 x too low)."""
    if not bins.size:
        return 0.0
    step = min(df, zeta * f0) / 20.0
    grid = np.arange(bins[0] - 0.5 * df, bins[-1] + 0.5 * df + step, step)
    return float(np.trapezoid(_oscillator(grid, f0, zeta), grid))


def _baseline(f: np.ndarray, p: np.ndarray, width: int, masked: np.ndarray, dof: int) -> np.ndarray:
    """Running median of log p over ``width`` bins, over the bins outside ``masked`` (the lines
    found so far, whose tails would raise it), interpolated across them, and divided by the
    median of a Welch PSD of ``dof`` degrees of freedom over its mean (chi^2/dof: 0.84 for one
    segment averaged over two axes, 4 dof): the threshold and the lines' excess are relative
    to the spectrum's mean, not its median (a 10 s record's white noise found two lines)."""
    keep = ~masked
    smooth = median_filter(np.log(np.maximum(p[keep], 1e-30)), size=width, mode="nearest")
    return np.exp(np.interp(f, f[keep], smooth)) / (chi2.median(dof) / dof)


def _candidates(f: np.ndarray, mean: np.ndarray, base: np.ndarray, inside: np.ndarray, threshold: float) -> list[int]:
    peaks = [i for i in np.flatnonzero(inside)[1:-1] if mean[i] >= mean[i - 1] and mean[i] >= mean[i + 1] and mean[i] > threshold * base[i]]
    return sorted(peaks, key=lambda i: -(mean[i] - base[i]))


@dataclass(frozen=True)
class LineSearch:
    """What the search found and how weak a line it could have found: ``limit_mas`` is the
    RMS per axis of the weakest line narrower than a bin, centred on one, that crosses the
    threshold at ``LIMIT_HZ`` (its PSD there, Hann's 1.5-bin noise bandwidth: sigma^2 =
    (threshold - 1) x baseline x 1.5 df), at least ``MIN_RMS_MAS``."""

    lines: list[LineEstimate]
    f: np.ndarray  # the frequencies and mean PSD the lines were found on (for the plots)
    mean_psd: np.ndarray
    limit_mas: float
    resolution_hz: float


LIMIT_HZ = 13.0  # where the detection limit is stated: LBT's principal line
HANN_ENBW_BINS = 1.5


def fit_lines(pol_tip_tilt_mas: np.ndarray, rate_hz: float) -> tuple[list[LineEstimate], np.ndarray, np.ndarray]:
    """The lines of the (frames, 2) pseudo-open-loop Tip/Tilt (mas), with the frequencies and
    the mean PSD they were found on (``search_lines`` without its detection limit)."""
    found = search_lines(pol_tip_tilt_mas, rate_hz)
    return found.lines, found.f, found.mean_psd


def search_lines(pol_tip_tilt_mas: np.ndarray, rate_hz: float) -> LineSearch:
    """The lines of the (frames, 2) pseudo-open-loop Tip/Tilt (mas) and the detection limit.
    The baseline is computed twice: the second time without the bins of the lines found the
    first time."""
    from scipy.signal import welch  # here, not at the top: the CLI starts without scipy.signal

    n = pol_tip_tilt_mas.shape[0]
    nperseg = int(min(2 ** round(math.log2(SEGMENT_S * rate_hz)), 2 ** int(math.log2(n))))
    f, p = welch(pol_tip_tilt_mas, fs=rate_hz, nperseg=nperseg, axis=0, detrend="linear")
    segments = max(1, n // nperseg)
    df = f[1] - f[0]
    width = max(5, int(2 * BASELINE_HZ / df) | 1)
    mean = p.mean(axis=1)
    inside = (f >= F_MIN_HZ) & (f <= 0.45 * rate_hz)
    threshold = chi2.isf(FALSE_ALARMS / max(1, inside.sum()), 4 * segments) / (4 * segments)  # two axes averaged
    masked = np.zeros(f.shape, dtype=bool)
    first = _baseline(f, mean, width, masked, 4 * segments)
    for i in _candidates(f, mean, first, inside, threshold)[:MAX_LINES]:
        _, zeta, _ = _fit_peak(f, mean, first, i)  # the line's width sets how much of it to mask
        masked |= np.abs(f - f[i]) <= max(1.0, 3 * df, MASK_WIDTHS * zeta * f[i])
    bases = np.stack([_baseline(f, p[:, a], width, masked, 2 * segments) for a in range(2)], axis=1)
    base = _baseline(f, mean, width, masked, 4 * segments)
    out: list[LineEstimate] = []
    model = base.copy()  # the baseline plus the lines fitted so far: a candidate they explain is their skirt
    for i in _candidates(f, mean, base, inside, threshold)[: 2 * MAX_LINES]:
        if len(out) == MAX_LINES:
            break
        if mean[i] <= threshold * model[i]:
            continue
        f0, zeta, sf = _fit_peak(f, mean, base, i)
        tip, tilt = (_axis_variance(f, p[:, a], bases[:, a], f0, zeta, segments) for a in range(2))
        model += 0.5 * (tip.value**2 + tilt.value**2) * _oscillator(f, f0, zeta)
        if max(tip.value, tilt.value) >= MIN_RMS_MAS:
            out.append(LineEstimate(Estimate(f0, max(sf, 0.0)), zeta, tip, tilt))
    at = int(np.argmin(np.abs(f - min(LIMIT_HZ, 0.45 * rate_hz))))
    limit = math.sqrt(max(threshold - 1.0, 0.0) * base[at] * HANN_ENBW_BINS * df)
    return LineSearch(sorted(out, key=lambda x: x.frequency.value), f, mean, max(limit, MIN_RMS_MAS), float(df))
