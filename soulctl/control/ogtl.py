"""Optical gain tracking loop (OGTL; Esposito et al. 2015, 2020; paper Sec. MGM).

A sinusoidal probe of known amplitude and frequency is added to the commands of one mode
(mode 30 by default, as at LBT).  The WFS measures that mode as m(k) = chi (x(k) - y(k)) + n(k),
x the turbulence, y the mirror's position of the mode during frame k, chi = gamma k the
optical gain times the slope sensitivity.  At the probe's frequency the turbulence and the
noise are uncorrelated with the probe, so demodulating m and y there gives

    chi_hat = -Re(M conj(Y)) / |Y|^2 ,   M, Y the lock-in (single-bin DFT) amplitudes,

and OGTL drives the sensitivity so that chi of the probed mode stays at 1 (the PWFS's unit
gain restored): log k <- log k - g log chi_hat, an integrator on the log of the error.  k is
held (not raised) while the RMS of the commands grows by more than 30 % from one update to the
next (``held_sensitivity``).

Probe defaults (a proposal; the paper gives none): 20 nm peak on mode 30, at a quarter of the
frame rate (425 Hz at 1700 Hz, 97.5 Hz at 390 Hz): well above the loop's bandwidth, so most of
the probe stays on the mirror, and far from the Tip/Tilt vibration lines and the 127 Hz
resonance, which do not act on mode 30 anyway.  20 nm peak is 14 nm RMS on one mode: a Strehl
loss below 0.3 % in H band.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .. import ranges

PROBE_MODE = 30  # 1-based, as the paper numbers modes
PROBE_AMPLITUDE_NM = 20.0
PROBE_FREQUENCY_PER_RATE = 0.25
SENSITIVITY_RANGE = (ranges.SENSITIVITY.lo, ranges.SENSITIVITY.hi)  # k's accepted range, ranges.SENSITIVITY


@dataclass(frozen=True)
class OgtlSettings:
    mode: int = PROBE_MODE  # 1-based
    amplitude_nm: float = PROBE_AMPLITUDE_NM
    frequency_hz: float | None = None  # None: a quarter of the frame rate
    gain: float = 0.5  # integrator gain on log k
    hold_growth: float = 1.3  # k is not raised while the commands' RMS grows by more than this per update

    def __post_init__(self):
        ranges.PROBE_MODE.check(self.mode, "--probe-mode")
        ranges.PROBE_AMPLITUDE_NM.check(self.amplitude_nm, "--probe-amplitude")
        if self.frequency_hz is not None and not (math.isfinite(self.frequency_hz) and self.frequency_hz > 0):
            raise InputError(f"--probe-frequency must be > 0 Hz and below Nyquist, got {self.frequency_hz:.10g}")
        if not (0 < self.gain <= 1):
            raise InputError(f"OGTL gain must be in 0..1 (> 0), got {self.gain:g}")
        if not (self.hold_growth >= 1):
            raise InputError(f"OGTL hold growth must be >= 1 (inf: never hold), got {self.hold_growth:g}")

    def probe_frequency(self, rate_hz: float) -> float:
        f = PROBE_FREQUENCY_PER_RATE * rate_hz if self.frequency_hz is None else self.frequency_hz
        if not f < 0.5 * rate_hz:
            raise InputError(f"--probe-frequency must be below Nyquist ({0.5 * rate_hz:g} Hz), got {f:.10g} Hz")
        return f


def demodulate(x: np.ndarray, frequency_hz: float, rate_hz: float, first_frame: int = 0) -> complex:
    """Lock-in amplitude of ``x`` (frames first_frame, first_frame + 1, ...) at ``frequency_hz``:
    2/N sum (x - mean) exp(-i 2 pi f k / rate), the probe's phase reference being frame 0."""
    x = np.asarray(x, dtype=float)
    k = first_frame + np.arange(x.size)
    return complex(2.0 / x.size * np.sum((x - x.mean()) * np.exp(-2j * np.pi * frequency_hz * k / rate_hz)))


def optical_gain_estimate(measured: np.ndarray, mirror: np.ndarray, frequency_hz: float, rate_hz: float, first_frame: int = 0) -> float:
    """chi_hat = -Re(M conj(Y)) / |Y|^2 of the probed mode (see the module docstring); nan when
    the mirror shows no probe."""
    M = demodulate(measured, frequency_hz, rate_hz, first_frame)
    Y = demodulate(mirror, frequency_hz, rate_hz, first_frame)
    if abs(Y) == 0:
        return math.nan
    return float(-(M * Y.conjugate()).real / abs(Y) ** 2)


def held_sensitivity(k_now: float, k_new: float, commands_rms: float, previous_rms: float | None, growth: float) -> tuple[float, bool]:
    """(k, held): k_new, except that k is not raised while the commands' RMS grew by more than
    ``growth`` since the previous update.  A loop leaving the PWFS's linear range loses optical
    gain; raising k then raises every effective gain and pushes it further out (the spiral of
    a poorly corrected loop); holding k breaks that feedback until the loop has settled."""
    if previous_rms is not None and k_new > k_now and commands_rms > growth * previous_rms:
        return k_now, True
    return k_new, False


def updated_sensitivity(k: float, chi_hat: float, gain: float) -> float:
    """log k <- log k - gain log chi_hat, clipped to the accepted range; k unchanged when the
    estimate is not a positive number."""
    if not (math.isfinite(chi_hat) and chi_hat > 0):
        return k
    lo, hi = SENSITIVITY_RANGE
    return float(min(hi, max(lo, k * chi_hat ** (-gain))))
