"""Loop delay, optical gains and measurement noise from the closed loop's noise rejection.

In closed loop the measurement is m/k = S (chi phi + n), S = 1 / (1 + g chi H z^-d) the
rejection of the mode (paper, Sec. 2.3; ``control.transfer``), H its unit-gain controller and
g its gain.  Above the band where the turbulence is rejected, chi phi is far below the white
measurement noise n and the PSD of m/k is sigma_n^2 |S|^2: the overshoot of |S| near the
loop's bandwidth and its ripple up to Nyquist carry the delay d and the product g chi.  The
controller (filters and gains) is known from the record, so d and chi follow.

Method: Whittle's likelihood of the Welch PSDs of every mode above ``f_low`` under the model
sigma_i^2 |S_i(f; d, chi_group)|^2, sigma_i^2 profiled out in closed form; one delay for all
modes, one chi per group of modes (``mode_groups``).  d is searched on a grid and refined by
a parabola, chi by a bounded scalar search at each d.  Uncertainties come from the curvature
of the likelihood, scaled by the record's independent segments (Welch bins of one segment
are chi-squared with ~2 x segments degrees of freedom).

Validity (docs/physics.md): the noise must dominate chi phi above f_low in the fitted modes
(faint stars, high modes; at the brightest, turbulence leaks in and chi is overestimated),
and g chi must give |S| a shape: a loop of very low gain has |S| ~ 1 everywhere and
identifies neither d nor chi (the estimate's uncertainty says so).  Tip/Tilt is left out of
the fit where the record holds other modes: vibration lines and the 127 Hz structure violate
the noise-only model at low frequencies.  A record of Tip/Tilt alone is fitted above
``ALONE_BANDS`` of the rate, the structure in the model (``_fit_alone``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.stats import chi2

from ..control.mgm import unit_open_loops
from .plant import Estimate
from .record import DELAY_SPAN, LoopRecord, delay_search

F_LOW_PER_RATE = 0.05  # f_low = 5 % of the frame rate (85 Hz at 1700 Hz, 49 Hz at 980 Hz)
DELAY_STEP = 0.05
COARSE_STEP = 0.25  # the first pass over a wide delay span (a record without a delay)
CHI_BOUNDS = (0.05, 4.0)
MODES_PER_GROUP = 40  # modes of a group the fit uses (evenly spread): speed, not accuracy
FIRST_MODE = 3  # 1-based; Tip/Tilt left out (see the module)


def mode_groups(n_modes: int) -> list[tuple[int, int]]:
    """(first, last) 1-based modes of the optical-gain groups, ~1.6x apart from mode 3: 3-5,
    6-9, 10-15, 16-24, 25-39, 40-62, 63-99, 100-159, 160-249, 250-399, 400-639, truncated to
    the record's modes (the optical gain varies slowly with the order; with half as many groups,
    3-9, 10-29, 30-89, 90-269, 270-, the probed mode's chi differed from its group's by up to
    17 %, 6 % and 11 % with these; docs/physics.md)."""
    edges = [FIRST_MODE, 6, 10, 16, 25, 40, 63, 100, 160, 250, 400, 640]
    out = []
    for lo, hi in zip(edges, edges[1:]):
        if lo > n_modes:
            break
        out.append((lo, min(hi - 1, n_modes)))
    return out


@dataclass(frozen=True)
class RejectionFit:
    delay: Estimate
    groups: tuple[tuple[int, int], ...]
    chi: tuple[Estimate, ...]  # per group, k divided out
    noise_nm2: np.ndarray  # per mode: variance of the measurement noise of m/k (nm^2 per frame), nan for Tip/Tilt
    f_low_hz: float
    excess_sensitivity: tuple[float, ...] = ()  # per group: relative chi change per 1 % excess (``_Likelihood.excess_sensitivity``)


class _Likelihood:
    """-log L (Whittle, sigma_i profiled) of the chosen modes as a function of d and chi."""

    def __init__(
        self, record: LoopRecord, modes: np.ndarray, f_low: float, structure: tuple | None = None, dropped: np.ndarray | None = None
    ):
        self.record, self.modes, self.structure = record, modes, structure
        band = record.f_hz >= f_low
        band[-1] = False  # the Nyquist bin has half the degrees of freedom
        if dropped is not None:
            band &= ~dropped
        self.f, self.p = record.f_hz[band], record.p_m[modes][:, band]
        self.weight = float(record.segments)  # nu / 2 with nu = 2 x independent segments
        self.filters = [record.filters[i] for i in modes]
        self.gains = record.gains[modes]
        self._cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    def parts(self, d: float) -> tuple[np.ndarray, np.ndarray]:
        """(2 Re gL, |gL|^2) per mode at delay d, chi = 1."""
        if d not in self._cache:
            L = self.gains[:, None] * unit_open_loops(
                self.filters, np.ones(len(self.modes)), self.record.loop.model_delay(d), self.record.rate_hz, self.f, self.structure
            )
            self._cache = {d: (2.0 * L.real, np.abs(L) ** 2)}
        return self._cache[d]

    def __call__(self, d: float, chi: float) -> float:
        a, b = self.parts(d)
        one_plus = np.maximum(1.0 + chi * a + chi * chi * b, 1e-12)  # |1 + chi g L|^2 = 1 / |S|^2
        sigma2 = np.mean(self.p * one_plus, axis=1)
        nll = self.p.shape[1] * np.log(sigma2).sum() - np.log(one_plus).sum()
        return float(self.weight * nll)

    def best_chi(self, d: float) -> tuple[float, float]:
        lo, hi = (math.log(x) for x in CHI_BOUNDS)
        res = minimize_scalar(lambda u: self(d, math.exp(u)), bounds=(lo, hi), method="bounded", options={"xatol": 1e-4})
        return math.exp(res.x), float(res.fun)

    def excess_sensitivity(self, d: float, chi: float) -> float:
        """Relative change of the fitted chi per 1 % excess of the PSD over the lower half of
        the band: the profiled Whittle fit's linear response, sum(u' x) / sum(u'^2) with
        u = d ln|S|^2 / d ln chi centred per mode (sigma_i absorbs a common offset)."""
        a, b = self.parts(d)
        u = -(chi * a + 2.0 * chi * chi * b) / np.maximum(1.0 + chi * a + chi * chi * b, 1e-12)
        u = u - u.mean(axis=1, keepdims=True)
        excess = np.where(self.f < np.median(self.f), 0.01, 0.0)
        return float(np.sum(u * excess) / max(float(np.sum(u * u)), 1e-300))

    def noise(self, d: float, chi: float) -> np.ndarray:
        a, b = self.parts(d)
        return np.mean(self.p * (1.0 + chi * a + chi * chi * b), axis=1)


def _spread(lo: int, hi: int) -> np.ndarray:
    modes = np.arange(lo - 1, hi)
    if len(modes) <= MODES_PER_GROUP:
        return modes
    return modes[np.unique(np.round(np.linspace(0, len(modes) - 1, MODES_PER_GROUP)).astype(int))]


def _curvature_sigma(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(vertex, 1-sigma) of a parabola through the lowest point of y(x) and its neighbours."""
    i = int(np.clip(np.argmin(y), 1, len(x) - 2))
    c2, c1, _ = np.polyfit(x[i - 1 : i + 2], y[i - 1 : i + 2], 2)
    if not c2 > 0:
        return float(x[np.argmin(y)]), math.inf
    return float(-c1 / (2 * c2)), float(1.0 / math.sqrt(2.0 * c2))


def fit_rejection(record: LoopRecord, f_low_hz: float | None = None) -> RejectionFit:
    """The delay, one chi per group and the noise of every fitted mode (see the module).  A
    record of Tip/Tilt alone (or of one mode) is fitted as one group (``_fit_alone``)."""
    groups = mode_groups(record.n_modes)
    if not groups:
        return _fit_alone(record, f_low_hz)
    f_low = F_LOW_PER_RATE * record.rate_hz if f_low_hz is None else f_low_hz
    fits = [_Likelihood(record, _spread(lo, hi), f_low) for lo, hi in groups]
    d_hat, d_sigma = _delay(fits, *delay_search(record.delay_frames))
    chis, leverage = _chis(record, fits, d_hat)
    return _with_noise(record, groups, fits, Estimate(d_hat, d_sigma), chis, f_low, leverage)


def _chis(record: LoopRecord, fits: list[_Likelihood], d_hat: float) -> tuple[list[Estimate], list[float]]:
    """chi of each group at the delay d_hat (k divided out), and its leverage (``excess_sensitivity``)."""
    chis, leverage = [], []
    for fit in fits:
        chi, _ = fit.best_chi(d_hat)
        leverage.append(fit.excess_sensitivity(d_hat, chi))
        u = np.log(chi) + np.array([-0.02, 0.0, 0.02])
        _, s = _curvature_sigma(u, np.array([fit(d_hat, math.exp(x)) for x in u]))
        k = record.sensitivity  # the fit's gain is k chi (m/k = S (chi phi + n), S with g k chi)
        chis.append(Estimate(chi / k, chi / k * s))  # sigma of log chi -> of chi
    return chis, leverage


def _with_noise(record: LoopRecord, groups: list, fits: list, delay: Estimate, chis: list, f_low: float, leverage: list) -> RejectionFit:
    """The fit with each mode's noise at the estimates (every mode of a group, not the spread ones)."""
    d_hat = delay.value
    noise = np.full(record.n_modes, np.nan)
    full = [_Likelihood(record, np.arange(lo - 1, hi), f_low, fit.structure) for (lo, hi), fit in zip(groups, fits)]
    for fit, est in zip(full, chis):
        noise[fit.modes] = 0.5 * record.rate_hz * fit.noise(d_hat, est.value * record.sensitivity)  # flat one-sided PSD 2 s^2 / rate
    return RejectionFit(delay, tuple(groups), tuple(chis), noise, f_low, tuple(leverage))


def _fit_alone(record: LoopRecord, f_low_hz: float | None) -> RejectionFit:
    """A record of Tip/Tilt alone (or of one mode): one group, the resonance in the model,
    fitted above ALONE_BANDS[0] of the rate, bins far above the first fit (lines: mains
    harmonics, fans) dropped and fitted again.  The fits above the other ALONE_BANDS give the
    estimates' systematic spread (coloured power above the loop's bandwidth moves chi with the
    band: on a real record by 25 % from 7 % to 15 % of the rate), added to their uncertainties."""
    modes, structure, groups = np.arange(record.n_modes), record.structure_ba, [(1, record.n_modes)]
    bands = (f_low_hz,) if f_low_hz is not None else tuple(b * record.rate_hz for b in ALONE_BANDS)
    results = []
    for f_low in bands:
        fit = _Likelihood(record, modes, f_low, structure)
        d_hat, _ = _delay([fit], *delay_search(record.delay_frames))
        fit = _Likelihood(record, modes, f_low, structure, _outliers(fit, d_hat))
        d_hat, d_sigma = _delay([fit], *delay_search(record.delay_frames))
        chis, leverage = _chis(record, [fit], d_hat)
        results.append((Estimate(d_hat, d_sigma), chis[0], leverage, fit))
    (delay, chi, leverage, fit), others = results[0], results[1:]
    if others:
        d_spread = 0.5 * (max(r[0].value for r in results) - min(r[0].value for r in results))
        c_spread = 0.5 * (max(r[1].value for r in results) - min(r[1].value for r in results))
        delay, chi = Estimate(delay.value, math.hypot(delay.sigma, d_spread)), Estimate(chi.value, math.hypot(chi.sigma, c_spread))
    return _with_noise(record, groups, [fit], delay, [chi], bands[0], leverage)


def _outliers(fit: _Likelihood, d: float) -> np.ndarray:
    """Bins (of the record's frequencies) whose mean whitened PSD, P |1 + chi g L|^2 / sigma^2,
    lies beyond what chance gives OUTLIER_FALSE_ALARMS times in the band (chi-squared of 2 x
    segments x modes degrees of freedom)."""
    chi, _ = fit.best_chi(d)
    a, b = fit.parts(d)
    one_plus = np.maximum(1.0 + chi * a + chi * chi * b, 1e-12)
    white = fit.p * one_plus
    ratio = np.mean(white / white.mean(axis=1, keepdims=True), axis=0)
    dof = 2 * fit.weight * len(fit.modes)
    threshold = chi2.isf(OUTLIER_FALSE_ALARMS / max(1, ratio.size), dof) / dof
    dropped = np.zeros(fit.record.f_hz.shape, dtype=bool)
    dropped[np.flatnonzero(fit.record.f_hz >= fit.f[0])[: ratio.size][ratio > threshold]] = True
    return dropped


def _delay(fits: list[_Likelihood], lo: float, hi: float) -> tuple[float, float]:
    """(d, sigma) where the profile likelihood (chi at its best for each d) is least, on a grid
    of DELAY_STEP; a wide span is searched at COARSE_STEP first, then around its minimum."""

    def profile(grid: np.ndarray) -> np.ndarray:
        return np.array([sum(fit.best_chi(float(d))[1] for fit in fits) for d in grid])

    if hi - lo > 2 * DELAY_SPAN:  # the record states no delay: coarse, then fine
        coarse = np.arange(lo, hi + 1e-9, COARSE_STEP)
        centre = float(coarse[np.argmin(profile(coarse))])
        lo, hi = max(lo, centre - 2 * COARSE_STEP), min(hi, centre + 2 * COARSE_STEP)
    grid = np.arange(lo, hi + 1e-9, DELAY_STEP)
    d_hat, d_sigma = _curvature_sigma(grid, profile(grid))
    return float(np.clip(d_hat, grid[0], grid[-1])), d_sigma


TIP_TILT_BAND = 0.15  # Tip/Tilt's noise from f >= 15 % of the frame rate: above the vibration lines
ALONE_BANDS = (0.10, 0.07, 0.15)  # a record of Tip/Tilt alone: its fit above 10 % of the rate, the others' spread
OUTLIER_FALSE_ALARMS = 0.01  # bins dropped from a Tip/Tilt-alone fit wrongly, per spectrum


def tip_tilt_noise(record: LoopRecord, delay_frames: float, chi: float) -> float:
    """Variance of Tip/Tilt's measurement noise (nm^2 per frame, mean of the axes, of m/k) at
    the given delay and chi, the structural resonance in the model."""
    fit = _Likelihood(record, np.arange(2), TIP_TILT_BAND * record.rate_hz, record.structure_ba)
    return float(np.mean(0.5 * record.rate_hz * fit.noise(delay_frames, chi * record.sensitivity)))
