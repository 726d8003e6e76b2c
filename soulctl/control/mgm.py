"""The Modal Gain Machine: per-mode optimal integrator gains from closed-loop telemetry.

For each controlled mode i, from the pseudo-open-loop (POL) modal time series recorded at fixed
gains (its reconstruction is not done here), MGM estimates the POL power spectral density
Phi_i(f) (Welch) and picks the gain that minimises (paper, Eq. cost)

    J_i(g) = sum_f |W_i(f, g)|^2 Phi_i(f),   W = 1 / (1 + g L1_i(f)),

with the unit-gain open loop (paper, Eq. plant)

    L1_i(f) = chi_i H_unit,i(e^{jw}) z^-d,   w = 2 pi f / rate,

chi_i the mode's optical gain times the slope sensitivity, H_unit,i its control filter at unit
gain and z^-d the loop delay, fractional delays as linear interpolation between frames
(``transfer.Plant``).  With a strictly causal loop (d >= 1) and white measurement noise,
sum |W|^2 Phi_pol is the variance of the measured residual, which is the variance of the true
residual plus a constant (the noise variance): its minimum is the true residual's.  The search
is over [0, (1 - margin) g_max,i], g_max,i the largest stable gain.  The RTC gain then moves
towards the optimum (paper, Eq. gainUpdate):

    g_RTC(kappa) = (1 - rho) g_RTC(kappa - 1) + rho nu g_hat(kappa).

Choices where the paper is silent:

* The filters' own gains are ignored: only their zeros and poles are used (the gain is what MGM
  chooses).  Each distinct (zeros, poles) filter is evaluated once.
* A loop stable for all gains (no finite g_max) gets the upper limit ``UNBOUNDED_LOOP_GAIN /
  chi_i`` (a loop gain g chi of 10), without margin.  A loop unstable at every gain gets 0.
* A mode whose PSD is identically zero (no signal) gets the gain 0: J is flat, and 0 is the
  first grid point; the refinement only replaces a grid optimum by a strictly better gain.
* The minimisation: J on a grid of ``grid`` gains uniform over [0, upper_i], then a golden-section
  search, all modes at once, over the two grid cells around the best grid point, with as many
  iterations as bring that bracket below ``REL_TOL * upper_i`` (13 for the default grid).
* J is estimated on the prewhitened POL (``ModalGainMachine.pol_psd``): each mode's POL is
  filtered by its control filter's denominator A_i(z) (for an integrator 1 - z^-1, a frame-to-
  frame difference) and J summed over the Welch frequencies *with* the DC bin, without
  detrending and without the factor df (it does not move the minimum):

      J_i(g) = sum_f Phi_{A pol, i}(f) / |A_i + g A_i L1_i|^2,

  the same J for the true spectra (|W|^2 = |A|^2 / |A + g A L1|^2), and A_i L1_i = chi_i B_i(z)
  z^-d is finite at DC.  Why: a low-order mode's turbulence is red and lies largely below the
  first Welch bin (at 5 m/s, under 0.5 Hz); a detrended Welch PSD of the POL drops that power,
  J loses the part a high gain rejects best and the optimum falls, most for the reddest modes.
  The prewhitened series keeps it (a slow drift of the POL is a mean of its difference, and a
  segment's energy holds all its frequencies), and the weight 1 / |A + g A L1|^2 is smooth over
  the window's two-bin kernel.  On a steady 10 s R13 record (980 Hz, 5 m/s) the detrended
  estimate's optimum for modes 3-10 grew with the segment, 0.40 / 0.44 / 0.49 / 0.53 at 256 /
  512 / 1024 / 2048 frames; the prewhitened one is 0.65-0.66 at all four (docs/physics.md).
  The frames before the window, which the first frames' prewhitening needs, are taken as the
  window's first frame.
* Noise-dominated modes (``noise_floor``, ``noise_dominated``): the WFS noise is white, so the
  POL PSD's floor, its median over the top quarter of the band (``FLOOR_BAND``, where the
  turbulence of every mode has fallen by decades), is the mode's noise level.  A mode whose
  POL power above that floor is below the noise's over the band (SNR < 1) gets at least the
  loop gain ``NOISE_LOOP_GAIN`` (g chi = 0.05, capped at the upper limit).  Why: the signal of
  such a mode is red and lives in the lowest Welch bins; with the short segments of a short
  window (64 frames at 250 Hz: 3.9 Hz bins) the detrended spectrum MGM first used put J's
  minimum at g = 0, the lower edge of the range, in 96-100 % of 250-frame windows for SNR
  0.05-0.9, where the true optimum is g chi = 0.02-0.11 and g = 0 leaves 2-9 times its
  residual; g chi = 0.05 stays within 1.4 times it over that SNR range, for delays of 1.5-3.5
  frames.  The prewhitened estimate keeps that signal and no longer reaches the edge; the
  floor stays as a guard (docs/physics.md, tests/control/test_mgm.py).
* A gain moves only when the move is significant (``improvement``, ``ModalGainMachine.significant``):
  the fall of J from the gain in force to g_hat, both read on the same PSD, must exceed
  ``significance`` (``SIGNIFICANCE``, 2) standard errors of that estimate; otherwise the mode
  keeps its gain, and Eq. gainUpdate (nu included) is not applied to it.  The standard error
  is Welch's for a Gaussian series (Hann window, 50 % overlap, neighbouring bins correlated),
  within 3 % of the scatter over 400 records (tests/control/test_mgm_significance.py).  Why:
  where J is flat, g_hat is set by the estimate's noise and the model's small errors rather
  than by the data.  At R14.5 1.0" (seed 2, with OGTL) MGM's updates predicted falls of J of
  0.0-0.5 %, about one standard error, and the gains they applied lost 0.021 in Strehl over 24
  windows; at R8 1.0" the predicted falls were 9-118 %, 3-8 standard errors, and MGM gained
  0.028 (``validation/mgm_updates.py``).  Trial-and-error keeps its incumbent unless another
  gain is significantly better: this is the same rule for MGM.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .filters import Filter
from .transfer import Loop, Plant, max_stable_gain

UNBOUNDED_LOOP_GAIN = 10.0  # g chi of a loop with no finite maximum stable gain
REL_TOL = 1e-4  # tolerance of the refined gain, relative to the upper limit
MIN_SEGMENTS = 4  # Welch segments a window must hold (50 % overlap)
FLOOR_BAND = 0.75  # the noise floor: the PSD's median above this fraction of Nyquist
NOISE_LOOP_GAIN = 0.05  # g chi at least, for a noise-dominated mode
MAX_GAIN_CHANGE = 2.0  # one update changes a mode's gain by at most this factor (up or down)
PSD_UPDATES = 5  # windows whose POL PSDs a live MGM averages (``loop.auxloops.MgmTask``)
SIGNIFICANCE = 2.0  # a gain moves only when MGM predicts J to fall by more than this many standard errors
_CHUNK_ELEMENTS = 131_072  # float64 elements per (modes, gains, frequencies) temporary: 1 MB, cache-sized
_INVPHI = (math.sqrt(5.0) - 1.0) / 2.0  # 0.618..., the golden-section ratio


@dataclass(frozen=True)
class MgmSettings:
    """The Modal Gain Machine's settings (paper, Eq. gainUpdate and Eq. cost).

    Parameters
    ----------
    nu, rho : float
        The update's factors: g(t+1) = (1 - rho) g(t) + rho nu g_hat (paper, Eq. gainUpdate).
    margin : float
        The stability margin: gains bounded at (1 - margin) of each mode's maximum stable gain.
    segment : int
        Welch segment of the pseudo-open-loop PSDs (frames, a power of two).
    grid : int
        Points of the coarse gain grid before the golden-section search.
    max_change : float
        The factor bounding one update of a gain (inf: Eq. gainUpdate alone).
    significance : float
        The standard errors a predicted fall of J must exceed for a gain to move (0: every
        gain moves).
    """

    nu: float = 0.9
    rho: float = 0.5
    margin: float = 0.1
    segment: int = 512  # Welch segment, frames
    grid: int = 48  # coarse gain grid points
    max_change: float = MAX_GAIN_CHANGE  # per update, as a factor (inf: Eq. gainUpdate alone)
    significance: float = SIGNIFICANCE  # standard errors (0: no test)

    def __post_init__(self):
        if not (0.0 < self.nu <= 1.0):
            raise InputError(f"MGM nu must be in (0, 1], got {self.nu!r}")
        if not (0.0 < self.rho <= 1.0):
            raise InputError(f"MGM rho must be in (0, 1], got {self.rho!r}")
        if not (0.0 <= self.margin < 1.0):
            raise InputError(f"MGM gain margin must be in [0, 1), got {self.margin!r}")
        s = self.segment
        if not (isinstance(s, (int, np.integer)) and not isinstance(s, bool) and 32 <= s <= 65536 and s & (s - 1) == 0):
            raise InputError(f"MGM PSD segment must be a power of two in 32..65536 frames, got {s!r}")
        g = self.grid
        if not (isinstance(g, (int, np.integer)) and not isinstance(g, bool) and g >= 8):
            raise InputError(f"MGM gain grid must be an integer >= 8 points, got {g!r}")
        if not (self.max_change > 1.0):
            raise InputError(f"MGM's largest change of a gain per update must be a factor > 1 (inf: none), got {self.max_change!r}")
        if not (0.0 <= self.significance <= 10.0):
            raise InputError(f"MGM's significance must be in 0..10 standard errors, got {self.significance!r}")


def min_frames(settings: MgmSettings) -> int:
    """Shortest telemetry window accepted: 4 Welch segments with 50 % overlap."""
    return settings.segment * (MIN_SEGMENTS + 1) // 2


def psd_frequencies(rate_hz: float, settings: MgmSettings) -> np.ndarray:
    """The frequencies (Hz) of the prewhitened POL PSD: the Welch bins from DC to Nyquist."""
    _check_rate(rate_hz)
    return np.fft.rfftfreq(settings.segment, 1.0 / rate_hz)


def _welch_settings(rate_hz: float, settings: MgmSettings) -> dict:
    """Hann window, 50 % overlap, no detrend, one-sided density."""
    s = settings.segment
    return dict(fs=rate_hz, window="hann", nperseg=s, noverlap=s // 2, detrend=False, return_onesided=True, scaling="density", axis=0)


def _checked_pol(pol, rate_hz: float, settings: MgmSettings) -> np.ndarray:
    """pol as a float array, or InputError: not (frames, modes), shorter than MIN_SEGMENTS
    segments, not finite."""
    _check_rate(rate_hz)
    pol = np.asarray(pol, dtype=float)
    if pol.ndim != 2 or pol.shape[1] < 1:
        raise InputError(f"POL telemetry must be a 2-D array (frames, modes), got shape {pol.shape}")
    n, need, s = pol.shape[0], min_frames(settings), settings.segment
    if n < need:
        raise InputError(
            f"telemetry window of {n} frames ({n / rate_hz:.3g} s) is shorter than {need} frames "
            f"({need / rate_hz:.3g} s): at least {MIN_SEGMENTS} PSD segments of {s} frames with 50 % overlap"
        )
    if not np.isfinite(pol).all():
        bad = np.nonzero(~np.isfinite(pol).all(axis=0))[0]
        raise InputError(f"POL telemetry must be finite: NaN or inf in {bad.size} mode(s), first mode {int(bad[0])}")
    return pol


def _fir(x: np.ndarray, a: np.ndarray, out: np.ndarray) -> None:
    """out(k) = sum_j a_j x(k - j) along the frames, x(k < 0) taken as x(0)."""
    np.multiply(x, a[0], out=out)
    for j in range(1, a.size):
        out[j:] += a[j] * x[:-j]
        out[:j] += a[j] * x[:1]


def _check_rate(rate_hz: float) -> None:
    if not (rate_hz > 0 and math.isfinite(rate_hz)):
        raise InputError(f"frame rate must be a finite number > 0 Hz, got {rate_hz!r}")


def _check_modes(filters, chi) -> np.ndarray:
    chi = np.asarray(chi, dtype=float)
    if chi.ndim != 1 or chi.size != len(filters) or chi.size < 1:
        raise InputError(f"chi must be a 1-D array with one value per filter ({len(filters)}), got shape {chi.shape}")
    if not (np.isfinite(chi).all() and (chi > 0).all()):
        raise InputError("chi (optical gain x slope sensitivity) must be finite and > 0 for every mode")
    for i, h in enumerate(filters):
        if not isinstance(h, Filter):
            raise InputError(f"filters must be soulctl Filter objects, got {type(h).__name__} for mode {i}")
    return chi


def _distinct(filters, structure) -> tuple[list[tuple], np.ndarray]:
    """The distinct (zeros, poles, structured) loops and each mode's index into them; the
    structural resonance applies to modes 0 and 1 (Tip/Tilt) only."""
    keys: dict[tuple, int] = {}
    idx = np.empty(len(filters), dtype=np.intp)
    for i, h in enumerate(filters):
        key = (tuple(h.zeros), tuple(h.poles), structure is not None and i < 2)
        idx[i] = keys.setdefault(key, len(keys))
    return list(keys), idx


def _plant(delay_frames: float, structure, structured: bool) -> Plant:
    if not structured:
        return Plant(delay_frames, 1.0, None)
    b, a = structure
    return Plant(delay_frames, 1.0, (tuple(float(c) for c in b), tuple(float(c) for c in a)))


def unit_open_loops(filters, chi, delay_frames: float, rate_hz: float, f, structure=None) -> np.ndarray:
    """L1_i(f) = chi_i H_unit,i z^-d (paper, Eq. plant), (n_modes, F) complex; ``structure``, a
    (b, a) resonance at this rate (``transfer.Plant``), multiplies the Tip/Tilt plants (modes 0, 1)."""
    A, M = whitened_open_loops(filters, chi, delay_frames, rate_hz, f, structure)
    return M / A


def whitened_open_loops(filters, chi, delay_frames: float, rate_hz: float, f, structure=None) -> tuple[np.ndarray, np.ndarray]:
    """(A_i(f), A_i L1_i(f)), each (n_modes, F) complex: A_i the denominator prod(1 - alpha z^-1)
    of mode i's filter, the prewhitening of its POL, and A_i L1_i = chi_i B_i(z) z^-d (B the
    numerator; with the Tip/Tilt resonance), finite where A_i = 0 (an integrator's DC)."""
    chi = _check_modes(filters, chi)
    _check_rate(rate_hz)
    w = 2.0 * np.pi * np.asarray(f, dtype=float) / rate_hz
    zi = np.exp(-1j * w)
    keys, idx = _distinct(filters, structure)
    plants = {s: _plant(delay_frames, structure, s).frequency_response(w) for s in {k[2] for k in keys}}
    coefficients = [(Filter(z, p, 1.0).coefficients(), s) for z, p, s in keys]
    den = np.stack([np.polyval(a[::-1], zi) for (_, a), _ in coefficients])
    num = np.stack([np.polyval(b[::-1], zi) * plants[s] for (b, _), s in coefficients])
    return den[idx], chi[:, None] * num[idx]


def gain_limits(filters, chi, delay_frames: float, rate_hz: float, margin: float, structure=None) -> np.ndarray:
    """Upper gain limit per mode, (1 - margin) g_max,i with g_max,i the maximum stable gain of
    Loop(H_unit,i, Plant(d, chi_i)): computed once per distinct loop at chi = 1 and divided by
    chi_i; a loop stable at all gains gets UNBOUNDED_LOOP_GAIN / chi_i."""
    chi = _check_modes(filters, chi)
    if not (0.0 <= margin < 1.0):
        raise InputError(f"MGM gain margin must be in [0, 1), got {margin!r}")
    keys, idx = _distinct(filters, structure)
    unit = np.array([max_stable_gain(Loop(Filter(z, p, 1.0), _plant(delay_frames, structure, s), rate_hz)) for z, p, s in keys])
    limit = np.where(np.isfinite(unit), (1.0 - margin) * unit, UNBOUNDED_LOOP_GAIN)
    return limit[idx] / chi


def psd_of_spectra(spectra: tuple[np.ndarray, np.ndarray, np.ndarray], a: float) -> np.ndarray:
    """The PSD of a m + c from ``ModalGainMachine.pol_spectra``: a^2 S_mm + S_cc + 2 a Re S_mc."""
    s_mm, s_cc, s_mc = spectra
    return a * a * s_mm + s_cc + 2.0 * a * s_mc


def _parts(psd, L1, whitening) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(psd, c, a, b) with |A + g L|^2 = c + g (a + g b): c = |A|^2, a = 2 Re(conj(A) L), b = |L|^2."""
    psd = np.asarray(psd, dtype=float)
    L1 = np.asarray(L1)
    A = np.ones(L1.shape) if whitening is None else np.asarray(whitening)
    if psd.ndim != 2 or L1.shape != psd.shape or A.shape != psd.shape:
        raise InputError(f"psd, L1 and the whitening must all be (n_modes, F) arrays, got shapes {psd.shape}, {L1.shape} and {A.shape}")
    return psd, A.real**2 + A.imag**2, 2.0 * (A.real * L1.real + A.imag * L1.imag), L1.real**2 + L1.imag**2


def _cost(psd, c, a, b, gains) -> np.ndarray:
    """J = sum_f psd / (c + g (a + g b)), real arithmetic; a term of zero denominator (an
    integrator's DC bin at g = 0) is inf where psd > 0 and 0 where psd = 0."""
    if gains.ndim == 1:
        den = c + gains[:, None] * (a + gains[:, None] * b)
        return np.sum(_ratio(psd, den), axis=1)
    n, G = gains.shape
    out = np.empty((n, G))
    step = max(1, _CHUNK_ELEMENTS // max(1, G * psd.shape[1]))
    for lo in range(0, n, step):
        s = slice(lo, lo + step)
        g = gains[s, :, None]
        den = b[s, None, :] * g
        den += a[s, None, :]
        den *= g
        den += c[s, None, :]
        out[s] = _ratio(np.broadcast_to(psd[s, None, :], den.shape), den).sum(axis=-1)
    return out


def _ratio(psd, den) -> np.ndarray:
    zero = den <= 0.0
    if not zero.any():
        return psd / den
    return np.where(zero, np.where(psd > 0.0, np.inf, 0.0), psd / np.where(zero, 1.0, den))


def cost(psd, L1, gains, whitening=None) -> np.ndarray:
    """J_i(g) = sum_f Phi_i(f) / |A_i(f) + g L1_i(f)|^2 (paper, Eq. cost; A = 1 unless
    ``whitening`` gives it: then Phi is the prewhitened POL's PSD and L1 the whitened open loop
    A L1); gains (n_modes,) gives (n_modes,), gains (n_modes, G) gives (n_modes, G)."""
    psd, c, a, b = _parts(psd, L1, whitening)
    gains = np.asarray(gains, dtype=float)
    if gains.ndim not in (1, 2) or gains.shape[0] != psd.shape[0]:
        raise InputError(f"gains must be (n_modes,) or (n_modes, G) with n_modes = {psd.shape[0]}, got shape {gains.shape}")
    return _cost(psd, c, a, b, gains)


def optimal_gains(psd, L1, upper, grid: int = MgmSettings.grid, whitening=None) -> np.ndarray:
    """g_hat_i = argmin J_i over [0, upper_i] (paper, Eq. cost; ``cost``): a grid of ``grid``
    gains, then a golden-section search over the grid cells around the best point, all modes
    at once, to REL_TOL * upper_i.  A mode with J flat (psd = 0) gets 0.

    Parameters
    ----------
    psd : ndarray, (n_modes, F)
        Phi_i(f): the pseudo-open loop's PSD of each mode (prewhitened with ``whitening``).
    L1 : ndarray, (n_modes, F)
        Each mode's open loop at unit gain at the PSD's frequencies.
    upper : ndarray, (n_modes,)
        Each mode's largest gain searched (its stability bound).
    grid : int
        Points of the coarse grid (>= 8).
    whitening : ndarray or None
        A_i(f), the prewhitening filter; None: A = 1.

    Returns
    -------
    ndarray, (n_modes,)
        The gains minimising J_i.
    """
    psd, c, a, b = _parts(psd, L1, whitening)
    upper = np.asarray(upper, dtype=float)
    if upper.shape != (psd.shape[0],) or not (np.isfinite(upper).all() and (upper >= 0).all()):
        raise InputError(f"upper gain limits must be finite, >= 0 and one per mode ({psd.shape[0]}), got shape {upper.shape}")
    if grid < 8:
        raise InputError(f"MGM gain grid must be an integer >= 8 points, got {grid!r}")
    rows = np.arange(psd.shape[0])
    steps = np.linspace(0.0, 1.0, grid)
    J = _cost(psd, c, a, b, upper[:, None] * steps[None, :])
    best = np.argmin(J, axis=1)
    g_grid, J_grid = upper * steps[best], J[rows, best]

    # Golden-section over [g_{best-1}, g_{best+1}] (clipped to the range), vectorised.
    lo = upper * steps[np.maximum(best - 1, 0)]
    hi = upper * steps[np.minimum(best + 1, grid - 1)]
    width = 2.0 / (grid - 1)
    iterations = max(1, math.ceil(math.log(REL_TOL / width) / math.log(_INVPHI)))
    x1 = hi - _INVPHI * (hi - lo)
    x2 = lo + _INVPHI * (hi - lo)
    J1, J2 = _cost(psd, c, a, b, x1), _cost(psd, c, a, b, x2)
    for _ in range(iterations):
        left = J1 < J2  # the minimum is in [lo, x2]: x2 <- x1, new x1; else in [x1, hi]: x1 <- x2, new x2
        hi = np.where(left, x2, hi)
        lo = np.where(left, lo, x1)
        x = np.where(left, hi - _INVPHI * (hi - lo), lo + _INVPHI * (hi - lo))
        Jx = _cost(psd, c, a, b, x)
        x1, x2 = np.where(left, x, x2), np.where(left, x1, x)
        J1, J2 = np.where(left, Jx, J2), np.where(left, J1, Jx)
    left = J1 < J2
    g_ref, J_ref = np.where(left, x1, x2), np.where(left, J1, J2)
    better = J_ref < J_grid  # ties (a flat J) keep the grid point
    return np.clip(np.where(better, g_ref, g_grid), 0.0, upper)


def noise_floor(psd, f, rate_hz: float) -> np.ndarray:
    """Per mode, the white-noise level of the POL PSD: its median over f >= FLOOR_BAND x Nyquist."""
    psd = np.asarray(psd, dtype=float)
    top = np.asarray(f) >= FLOOR_BAND * 0.5 * rate_hz
    return np.median(psd[:, top], axis=1) if top.any() else np.zeros(psd.shape[0])


def noise_dominated(psd, floor) -> np.ndarray:
    """Per mode, True when the POL power above the noise floor, sum max(Phi - floor, 0), is below
    the noise's over the band, floor x F."""
    psd = np.asarray(psd, dtype=float)
    signal = np.sum(np.maximum(psd - floor[:, None], 0.0), axis=1)
    return signal < floor * psd.shape[1]


def update_gains(previous, optimum, settings: MgmSettings, moves=None) -> np.ndarray:
    """g_RTC(kappa) = (1 - rho) g_RTC(kappa - 1) + rho nu g_hat(kappa) (paper, Eq. gainUpdate),
    within a factor ``max_change`` of g_RTC(kappa - 1): an RTC's smoothing of the update.

    Why the bound: one update from a short, noise-dominated window can put g_hat 10x above the
    gains in force (R16.5, 275 frames, 88 of 90 modes noise-dominated: Tip/Tilt 0.117/0.113 ->
    0.947/0.446), and a loop so far outside the PWFS's linear range (residual ~1 um, optical
    gain 0.07) ran away in ~10 s at the new gains.  Eq. gainUpdate with rho = 0.5 moves at most
    ~halfway per update anyway, so the bound acts only on such jumps; a factor 2 still brings
    0.1x the optimum within 10 % of it in 5 updates (the unbounded rule in 4), 25 s at the
    paper's 5 s cadence (its "about a minute").  A mode at gain 0 is not bounded.  ``moves``
    (per mode, e.g. ``ModalGainMachine.significant``): the modes whose gain changes; the
    others keep ``previous``."""
    previous = np.asarray(previous, dtype=float)
    optimum = np.asarray(optimum, dtype=float)
    if previous.shape != optimum.shape:
        raise InputError(f"previous and optimal gains must have the same shape, got {previous.shape} and {optimum.shape}")
    gains = (1.0 - settings.rho) * previous + settings.rho * settings.nu * optimum
    if not math.isinf(settings.max_change):
        clipped = np.clip(gains, previous / settings.max_change, previous * settings.max_change)
        gains = np.where(previous > 0, clipped, gains)  # a mode at gain 0 (not controlled): Eq. gainUpdate alone
    return gains if moves is None else np.where(moves, gains, previous)


def segments_of(frames: int, settings: MgmSettings) -> int:
    """Welch segments (50 % overlap) in a window of ``frames`` frames."""
    half = settings.segment // 2
    return max(0, (frames - half) // half)


@functools.lru_cache(maxsize=16)
def _welch_correlations(segment: int) -> tuple[float, float, float]:
    """(overlap, r1, r2) of a Hann-window Welch estimate of a Gaussian series: the squared
    correlation of two half-overlapping segments' periodograms (1/36) and of one periodogram's
    bins 1 and 2 apart (4/9, 1/36), computed from the window as ``welch`` uses it."""
    from scipy.signal import get_window  # here, not at the top: the CLI starts without scipy.signal

    w = get_window("hann", segment)
    w2 = np.sum(w * w)
    n = np.arange(segment)
    overlap = (np.sum(w[: segment // 2] * w[segment // 2 :]) / w2) ** 2
    r1, r2 = (abs(np.sum(w * w * np.exp(-2j * np.pi * m * n / segment))) ** 2 / w2**2 for m in (1, 2))
    return float(overlap), float(r1), float(r2)


def mean_psd_variance(segments: Sequence[int], segment: int) -> float:
    """Var(Phi_mean) / Phi^2 of the mean of Welch PSDs of windows with these segment counts
    (Welch 1967: (1 + 2 c (K - 1) / K) / K per window, c the overlap's squared correlation)."""
    overlap = _welch_correlations(segment)[0]
    per_window = [(1.0 + 2.0 * overlap * (k - 1) / k) / k for k in segments if k > 0]
    if not per_window:
        raise InputError("MGM's significance needs at least one window of one Welch segment")
    return float(np.sum(per_window) / len(per_window) ** 2)


def improvement(psd, L1, gains_now, gains_hat, variance: float, whitening=None) -> tuple[np.ndarray, np.ndarray]:
    """Per mode, J(g_now) - J(g_hat) (Eq. cost) from the PSD estimate ``psd`` (on the Welch bins
    of a 2 (F - 1)-frame segment) and its standard error: the difference is sum_f d(f) Phi(f),
    d the difference of the two weights, and Phi's bins scatter by sqrt(variance) x Phi
    (``mean_psd_variance``), neighbours correlated by the Hann window (``_welch_correlations``)."""
    psd, c, a, b = _parts(psd, L1, whitening)
    now, hat = (np.asarray(g, dtype=float)[:, None] for g in (gains_now, gains_hat))
    j_now, j_hat = (_ratio(psd, c + g * (a + g * b)) for g in (now, hat))
    with np.errstate(invalid="ignore"):
        v = j_now - j_hat
    delta = np.sum(j_now, axis=1) - np.sum(j_hat, axis=1)  # inf where g_now leaves a powered DC bin unrejected
    v = np.where(np.isfinite(v), v, 0.0)
    _, r1, r2 = _welch_correlations(2 * (psd.shape[1] - 1))
    quadratic = np.sum(v * v, axis=1) + 2 * r1 * np.sum(v[:, 1:] * v[:, :-1], axis=1) + 2 * r2 * np.sum(v[:, 2:] * v[:, :-2], axis=1)
    return np.where(np.isnan(delta), 0.0, delta), np.sqrt(np.maximum(quadratic, 0.0) * variance)


@dataclass(frozen=True, eq=False)
class ModalGainMachine:
    """MGM for one set of controlled modes: unit-gain filters (one per mode; their gains are
    ignored), chi per mode, the loop delay (frames) and rate; ``structure`` an optional (b, a)
    resonance of the Tip/Tilt plants.  The gain limits, the prewhitening filters A_i and the
    whitened open loops A_i L1_i on the Welch frequencies are computed once, at construction."""

    filters: tuple[Filter, ...]
    chi: np.ndarray
    delay_frames: float
    rate_hz: float
    settings: MgmSettings = field(default_factory=MgmSettings)
    structure: tuple | None = None
    upper: np.ndarray = field(init=False, repr=False)
    frequencies: np.ndarray = field(init=False, repr=False)
    whitening: np.ndarray = field(init=False, repr=False)
    open_loops: np.ndarray = field(init=False, repr=False)

    def __post_init__(self):
        filters = tuple(self.filters)
        chi = _check_modes(filters, self.chi)
        chi.setflags(write=False)
        f = psd_frequencies(self.rate_hz, self.settings)
        upper = gain_limits(filters, chi, self.delay_frames, self.rate_hz, self.settings.margin, self.structure)
        A, M = whitened_open_loops(filters, chi, self.delay_frames, self.rate_hz, f, self.structure)
        for name, value in (("filters", filters), ("chi", chi), ("upper", upper), ("frequencies", f), ("whitening", A), ("open_loops", M)):
            if isinstance(value, np.ndarray):
                value.setflags(write=False)
            object.__setattr__(self, name, value)

    @property
    def n_modes(self) -> int:
        return len(self.filters)

    def prewhitened(self, pol, modes: slice = slice(None)) -> np.ndarray:
        """A_i(z) applied to each mode's series, pol (frames, modes) the machine's ``modes``; the
        frames before the window are taken as its first frame (an integrator's difference starts
        at 0), so that the series keeps its length and each mode its own prewhitening."""
        pol = _checked_pol(pol, self.rate_hz, self.settings)
        filters = self.filters[modes]
        if pol.shape[1] != len(filters):
            raise InputError(f"POL telemetry must be (frames, {len(filters)}) for {len(filters)} modes, got shape {pol.shape}")
        keys, idx = _distinct(filters, None)
        out = np.empty_like(pol)
        for j, (_, poles, _) in enumerate(keys):
            cols = np.flatnonzero(idx == j)
            a = Filter((), poles, 1.0).coefficients()[1]
            if cols[-1] - cols[0] + 1 == cols.size:  # contiguous: filtered in place
                _fir(pol[:, cols[0] : cols[-1] + 1], a, out[:, cols[0] : cols[-1] + 1])
            else:
                part = np.empty((pol.shape[0], cols.size))
                _fir(pol[:, cols], a, part)
                out[:, cols] = part
        return out

    def pol_psd(self, pol, modes: slice = slice(None)) -> np.ndarray:
        """The Welch PSD (modes, F) of the prewhitened POL series pol (frames, modes) of the
        machine's ``modes``, on ``frequencies`` (Hann window, no detrend, one-sided density)."""
        from scipy.signal import welch

        y = self.prewhitened(pol, modes)
        return np.ascontiguousarray(welch(y, **_welch_settings(self.rate_hz, self.settings))[1].T)

    def pol_spectra(self, measured, shifted) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The prewhitened POL PSD in parts, for a POL a m + c whose scale a is chosen later: the
        Welch densities of A m and of A c and the real part of their cross density.  Welch is
        a quadratic form of the windowed segments, so ``psd_of_spectra(spectra, a)`` is exactly
        ``pol_psd(a m + c)``."""
        from scipy.signal import csd, welch

        m, c = self.prewhitened(measured), self.prewhitened(shifted)
        kw = _welch_settings(self.rate_hz, self.settings)
        parts = (welch(m, **kw)[1], welch(c, **kw)[1], csd(m, c, **kw)[1].real)
        return tuple(np.ascontiguousarray(p.T) for p in parts)  # type: ignore[return-value]

    def optimum(self, pol) -> tuple[np.ndarray, dict]:
        """(g_hat, info) from the POL series pol (frames, n_modes); info holds f (Hz), psd
        (n_modes, F; the prewhitened POL's), upper (the gain limits), noise_floor (per mode) and
        noise_dominated (the modes given at least NOISE_LOOP_GAIN / chi)."""
        return self.optimum_of_psd(self.pol_psd(pol))

    def optimum_of_psd(self, psd) -> tuple[np.ndarray, dict]:
        """``optimum`` from a prewhitened POL PSD already estimated (n_modes, F) on
        ``frequencies``: one window's (``pol_psd``) or the mean of several windows'
        (``loop.auxloops.MgmTask``).  The noise rule reads the POL PSD psd / |A|^2 above DC."""
        psd = np.asarray(psd, dtype=float)
        if psd.shape != (self.n_modes, self.frequencies.size):
            raise InputError(f"POL PSD must be ({self.n_modes}, {self.frequencies.size}), got shape {psd.shape}")
        f = self.frequencies
        gains = optimal_gains(psd, self.open_loops, self.upper, self.settings.grid, self.whitening)
        A = self.whitening[:, 1:]
        pol = psd[:, 1:] / (A.real**2 + A.imag**2)
        floor = noise_floor(pol, f[1:], self.rate_hz)
        noisy = noise_dominated(pol, floor)
        gains = np.where(noisy, np.maximum(gains, np.minimum(NOISE_LOOP_GAIN / self.chi, self.upper)), gains)
        return gains, {"f": f, "psd": psd, "upper": self.upper, "noise_floor": floor, "noise_dominated": noisy}

    def significant(self, psd, gains_now, gains_hat, segments: Sequence[int]) -> np.ndarray:
        """Per mode, whether J(g_hat) is below J(g_now) by more than ``settings.significance``
        standard errors (``improvement``) of the mean PSD ``psd`` of windows of ``segments``
        Welch segments each; every mode when the significance is 0."""
        if self.settings.significance == 0:
            return np.ones(self.n_modes, dtype=bool)
        variance = mean_psd_variance(segments, self.settings.segment)
        delta, se = improvement(psd, self.open_loops, gains_now, gains_hat, variance, self.whitening)
        return delta > self.settings.significance * se

    def step(self, previous_gains, pol) -> np.ndarray:
        """New RTC gains: Eq. gainUpdate from the previous gains and the optimum of pol, for
        the modes where the optimum is significantly better (``significant``)."""
        psd = self.pol_psd(pol)
        gains, _ = self.optimum_of_psd(psd)
        moves = self.significant(psd, previous_gains, gains, [segments_of(np.shape(pol)[0], self.settings)])
        return update_gains(previous_gains, gains, self.settings, moves)
