"""Optical gain tracking loop (OGTL; Esposito et al. 2015, 2020; paper Sec. MGM).

A sinusoidal probe of known amplitude and frequency is added to the commands of one mode
(mode 30 by default, as at LBT).  The WFS measures that mode as m(k) = chi (x(k) - y(k)) + n(k),
x the turbulence, y the mirror's position of the mode during frame k, chi = gamma k the
optical gain times the slope sensitivity.  At the probe's frequency the turbulence and the
noise are uncorrelated with the probe, so demodulating m and y there gives

    chi_hat = -Re(M conj(Y)) / |Y|^2 ,   M, Y the lock-in (single-bin DFT) amplitudes,

and OGTL drives the sensitivity so that chi of the probed mode stays at 1 (the PWFS's unit
gain restored): log k <- log k - g log chi_hat, an integrator on the log of the error.

OGTL knows when it does not know (``estimate``, ``next_sensitivity``):

* *Reliability*: the lock-in's noise is measured in the same window at ``REFERENCE_BINS``
  off-frequency bins of m after the fitted probe is removed; its spread along Y gives the
  standard error sigma_chi and the SNR chi_hat / sigma_chi.  k moves only when SNR >=
  ``min_snr`` (5: a 20 % error of one estimate, 10 % on k after the 0.5 integrator gain);
  otherwise it is held.
* *Bounds*: k stays in [1, k_max]: no PWFS has an optical gain above 1, and k_max = 1 /
  gamma_probe at ``WORST_SEEING_ARCSEC``, the lowest optical gain the optical model gives the
  configuration's probed mode (set by the builder of the task).
* *Rate*: one update changes k by at most a factor ``max_step`` (1.5): one wrong estimate
  cannot move it far, and k still reaches 1 / gamma = 5 from 1 in four updates.
* *Spiral*: when k was raised by ``SPIRAL_RAISE`` (20 %) or more since the last reliable
  estimate and chi_hat has not risen with it, the loop lost more optical gain than k added:
  raising k raised every effective gain, the residual grew and the PWFS's gain fell (a poorly
  corrected, noise-dominated loop).  k goes back to its value at that estimate and is not
  raised past it for the next ``SPIRAL_HOLD`` (5) reliable estimates, twice as many after each
  further spiral.  Why it expires: at the threshold SNR of 5 chi_hat scatters by 20 %, so a
  true 20 % rise of chi is missed about one time in four; a ceiling that never expired held
  k at 1.5 for a whole R16.5 run (at 4.3-4.9 in the other seeds) and below 1.95 at R17.5.  A
  true spiral comes back when the ceiling lifts and is caught again, each time after twice
  as long.  Near convergence the steps are small and the rule is idle, so it does not bias k.
  Nor is a raise judged that leaves k at or below ``k_model``, 1 / gamma_probe of the optical
  model at the plant model's seeing (from the task's builder): up to it every effective gain
  stays at or below its design, which cannot over-drive the loop.  Judged there, one
  low estimate after the first raise from 1 (R16.5, SNR near 5) held k at 1-1.5 for the run's
  settling and MGM tuned its gains at k = 1, a fifth of the optical gain's compensation.
* *Growth*: k is not raised while the commands' RMS grows by more than 30 % from one update to
  the next.
* *NCPA offsets*: reference-slope offsets wait until a reliable estimate puts the probed
  mode's chi within ``OFFSETS_CHI_TOLERANCE`` (20 %) of 1, as SOUL applies them once k is
  calibrated: at k = 1 they are over-applied by 1 / gamma (``optics.ncpa``), and at R9.7 with
  100 nm applied from the first frame the loop lost lock (H Strehl 0.08, residual 1.65 um).
  In force, they are scaled by the latest estimate of chi = k gamma (``offset_scale``), so
  that a k the rules hold below 1 / gamma does not over-apply them; and the spiral rule does
  not compare the estimates on either side of their entry (the NCPA they put into the WFS
  path lowers gamma by design, not because k was raised).
Every update records its status (``STATUS``: why k moved less than the integrator asked).

Probe defaults (``default_amplitude``, ``PROBE_FREQUENCY_PER_RATE``): at a quarter of the
frame rate (425 Hz at 1700 Hz, 62.5 Hz at 250 Hz), above the loop's bandwidth so that most of
the probe stays on the mirror, and far from the Tip/Tilt vibration lines and the 127 Hz
resonance, which do not act on mode 30 anyway; the amplitude is 20 nm peak (14 nm RMS, a
Strehl loss below 0.3 % in H band) or, where the WFS noise of the probed mode needs more for
the reliability threshold in one update period, the amplitude that reaches it, at most
``MAX_DEFAULT_AMPLITUDE_NM``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .. import ranges
from ..errors import InputError

PROBE_MODE = 30  # 1-based, as the paper numbers modes
PROBE_AMPLITUDE_NM = 20.0  # the default probe's amplitude where the noise allows it
MAX_DEFAULT_AMPLITUDE_NM = 80.0  # the default probe's amplitude at most (57 nm RMS on one mode)
PROBE_FREQUENCY_PER_RATE = 0.25
SENSITIVITY_RANGE = (ranges.SENSITIVITY.lo, ranges.SENSITIVITY.hi)  # k's accepted range, ranges.SENSITIVITY
MIN_SENSITIVITY = 1.0  # k below 1 would mean an optical gain above 1
WORST_SEEING_ARCSEC = 2.0  # k_max = 1 / gamma_probe at this seeing (SOUL's nights: DIMM <= 1.6")
MIN_SNR = 5.0  # an estimate moves k only from this SNR on
MAX_STEP = 1.5  # k changes by at most this factor per update
SPIRAL_RAISE = 1.2  # a raise of k since the last reliable estimate that chi must follow
SPIRAL_HOLD = 5  # reliable estimates a spiral's ceiling on k lasts (doubled at each further spiral)
OFFSETS_CHI_TOLERANCE = 0.2  # NCPA offsets are applied once the probed mode's |chi - 1| is this or less
REFERENCE_BINS = (-6, -5, -4, -3, 3, 4, 5, 6)  # off-frequency bins (of the window) of the noise reference
# Why an update moved k less than the integrator asked (recorded per update as ``status``).
STATUS = (
    "updated",
    "held: probe SNR below the threshold",
    "held: commands growing",
    "held: no estimate",
    "step limited",
    "at a bound",
    "lowered: raising k lost optical gain",
)
UPDATED, LOW_SNR, GROWING, NO_ESTIMATE, STEP_LIMITED, AT_BOUND, SPIRAL = range(len(STATUS))
# The statuses of an update that did not act on an estimate (none, or one OGTL does not trust):
# k has not been calibrated by it, and an optimiser waits for one that did (``OgtlTask.calibrated``).
HELD = frozenset((LOW_SNR, GROWING, NO_ESTIMATE))


@dataclass(frozen=True)
class OgtlSettings:
    mode: int = PROBE_MODE  # 1-based
    amplitude_nm: float | None = None  # None: ``default_amplitude`` for the operating point
    frequency_hz: float | None = None  # None: a quarter of the frame rate
    gain: float = 0.5  # integrator gain on log k
    hold_growth: float = 1.3  # k is not raised while the commands' RMS grows by more than this per update
    min_snr: float = MIN_SNR
    max_step: float = MAX_STEP

    def __post_init__(self):
        ranges.PROBE_MODE.check(self.mode, "--probe-mode")
        if self.amplitude_nm is not None:
            ranges.PROBE_AMPLITUDE_NM.check(self.amplitude_nm, "--probe-amplitude")
        if self.frequency_hz is not None and not (math.isfinite(self.frequency_hz) and self.frequency_hz > 0):
            raise InputError(f"--probe-frequency must be > 0 Hz and below Nyquist, got {self.frequency_hz:.10g}")
        if not (0 < self.gain <= 1):
            raise InputError(f"OGTL gain must be in 0..1 (> 0), got {self.gain:g}")
        if not (self.hold_growth >= 1):
            raise InputError(f"OGTL hold growth must be >= 1 (inf: never hold), got {self.hold_growth:g}")
        if not (self.min_snr >= 0 and self.max_step > 1):
            raise InputError(f"OGTL needs min_snr >= 0 and max_step > 1, got {self.min_snr:g} and {self.max_step:g}")

    def probe_frequency(self, rate_hz: float) -> float:
        f = PROBE_FREQUENCY_PER_RATE * rate_hz if self.frequency_hz is None else self.frequency_hz
        if not f < 0.5 * rate_hz:
            raise InputError(f"--probe-frequency must be below Nyquist ({0.5 * rate_hz:g} Hz), got {f:.10g} Hz")
        return f


def default_amplitude(noise_nm: float, optical_gain: float, frames: int, min_snr: float = MIN_SNR) -> float:
    """The default probe amplitude (nm peak): ``PROBE_AMPLITUDE_NM``, or the amplitude a whose
    lock-in over ``frames`` frames of white noise of ``noise_nm`` RMS per frame (the probed
    mode's WFS noise at k = 1) reaches twice ``min_snr`` at the expected optical gain:
    SNR = gamma a / (noise sqrt(2 / N)), capped at ``MAX_DEFAULT_AMPLITUDE_NM``."""
    if not (noise_nm >= 0 and optical_gain > 0 and frames > 0):
        return PROBE_AMPLITUDE_NM
    need = 2.0 * min_snr * noise_nm * math.sqrt(2.0 / frames) / optical_gain
    return float(min(MAX_DEFAULT_AMPLITUDE_NM, max(PROBE_AMPLITUDE_NM, need)))


def demodulate(x: np.ndarray, frequency_hz: float, rate_hz: float, first_frame: int = 0) -> complex:
    """Lock-in amplitude of ``x`` (frames first_frame, first_frame + 1, ...) at ``frequency_hz``:
    2/N sum (x - mean) exp(-i 2 pi f k / rate), the probe's phase reference being frame 0."""
    x = np.asarray(x, dtype=float)
    k = first_frame + np.arange(x.size)
    return complex(2.0 / x.size * np.sum((x - x.mean()) * np.exp(-2j * np.pi * frequency_hz * k / rate_hz)))


def optical_gain_estimate(measured: np.ndarray, mirror: np.ndarray, frequency_hz: float, rate_hz: float, first_frame: int = 0) -> float:
    """chi_hat = -Re(M conj(Y)) / |Y|^2 of the probed mode (see the module docstring); nan when
    the mirror shows no probe."""
    return estimate(measured, mirror, frequency_hz, rate_hz, first_frame).chi


@dataclass(frozen=True)
class Estimate:
    """One lock-in estimate: chi_hat, its standard error and their ratio (nan: no estimate)."""

    chi: float
    sigma: float
    snr: float


def estimate(measured: np.ndarray, mirror: np.ndarray, frequency_hz: float, rate_hz: float, first_frame: int = 0) -> Estimate:
    """chi_hat (``optical_gain_estimate``) with its standard error: the noise of the lock-in at
    the probe's frequency is taken as that at ``REFERENCE_BINS`` off-frequency bins of the
    window, in m less its fitted probe (a complex amplitude of variance s^2 has s^2 / 2 along
    Y): sigma_chi = sqrt(mean |M_off|^2 / 2) / |Y|."""
    m = np.asarray(measured, dtype=float)
    n = m.size
    M = demodulate(m, frequency_hz, rate_hz, first_frame)
    Y = demodulate(mirror, frequency_hz, rate_hz, first_frame)
    if abs(Y) == 0 or n < 2:
        return Estimate(math.nan, math.nan, math.nan)
    chi = float(-(M * Y.conjugate()).real / abs(Y) ** 2)
    k = first_frame + np.arange(n)
    rest = m - (M * np.exp(2j * np.pi * frequency_hz * k / rate_hz)).real  # m less the probe it shows
    bin_hz = rate_hz / n
    off = [frequency_hz + b * bin_hz for b in REFERENCE_BINS]
    off = [f for f in off if 0 < f < 0.5 * rate_hz]
    if not off:
        return Estimate(chi, math.nan, math.nan)
    power = np.mean([abs(demodulate(rest, f, rate_hz, first_frame)) ** 2 for f in off])
    sigma = float(math.sqrt(power / 2.0) / abs(Y))
    snr = abs(chi) / sigma if sigma > 0 else math.inf
    return Estimate(chi, sigma, float(snr))


def next_sensitivity(k: float, est: Estimate, settings: OgtlSettings, k_max: float, growing: bool = False) -> tuple[float, int]:
    """(k, status) of one OGTL update (see the module docstring): the integrator
    log k <- log k - gain log chi_hat when the estimate is reliable, its change limited to a
    factor ``max_step``, k kept in [MIN_SENSITIVITY, k_max]; not raised while ``growing``."""
    hi = min(k_max, SENSITIVITY_RANGE[1])
    lo = MIN_SENSITIVITY
    bounded = float(min(hi, max(lo, k)))
    if not (math.isfinite(est.chi) and est.chi > 0):
        return bounded, NO_ESTIMATE
    if not est.snr >= settings.min_snr:
        return bounded, LOW_SNR
    wanted = k * est.chi ** (-settings.gain)
    if growing and wanted > k:
        return bounded, GROWING
    step = min(settings.max_step, max(1.0 / settings.max_step, wanted / k))
    new = k * step
    status = UPDATED if step == wanted / k else STEP_LIMITED
    if not lo <= new <= hi:
        new, status = min(hi, max(lo, new)), AT_BOUND
    return float(new), status


def spiralling(k: float, chi: float, last: tuple[float, float] | None, k_model: float = MIN_SENSITIVITY) -> bool:
    """True when k was raised by SPIRAL_RAISE or more since ``last`` = (k, chi_hat) of the last
    reliable estimate, past ``k_model``, and chi_hat did not rise with it (see the module docstring)."""
    return last is not None and k > k_model and k >= SPIRAL_RAISE * last[0] and chi <= last[1]


def offset_scale(chi_now: float) -> float:
    """The NCPA offsets' scale: OGTL's latest estimate of k gamma of the probed mode, at most 1.
    The loop settles where k gamma_i D a_wfs = -scale D a, so the mirror applies -a scale /
    (k gamma_i): the aberration itself when the scale is k gamma, whatever k.  Unscaled, a k
    held below 1 / gamma (by the spiral or growth rules, or a low-SNR hold) over-applies the
    offsets by 1 / (k gamma); the larger residual lowers gamma and the loop runs away (R9.4,
    1.33\": k held at 2.25 while k gamma fell from 0.52 to 0.21, diverged after 12 s)."""
    return min(1.0, max(0.0, chi_now))


def commands_growing(commands_rms: float, previous_rms: float | None, growth: float) -> bool:
    """True when the commands' RMS grew by more than ``growth`` since the previous update: a
    loop leaving the PWFS's linear range loses optical gain; raising k then raises every
    effective gain and pushes it further out; holding k breaks that feedback."""
    return previous_rms is not None and commands_rms > growth * previous_rms
