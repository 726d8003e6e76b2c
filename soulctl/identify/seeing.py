"""r0 (seeing at 500 nm) and L0 from the pseudo-open-loop modal variances.

The von Karman variance of mode i is V_i(L0) r0^(-5/3) (rad^2 at 500 nm), V_i the variance
of the mode's coefficient for r0 = 1 m: for the record's own modal basis (soulctl's KL modes
of the configuration) V_i = s_i^T C(L0) s_i / n_p^2 over the pupil pixels, C the von Karman
phase covariance (``optics.atmosphere``) applied by FFT convolution as the KL construction
does (``optics.asm``); for a foreign basis, the Zernike variances of the same radial order
(Noll 1976, Kolmogorov: 0.7632... (n + 1) Gamma(n - 5/6) / Gamma(n + 23/6) (D/r0)^(5/3)),
an approximation that ignores the central obstruction and L0 (L0 is then not estimated).

The pseudo-open-loop variance of each mode, less its measurement noise (noise / chi^2), is
fitted in log by log r0^(-5/3) + log V_i(L0) over modes ``FIRST_MODE``.. (Tip/Tilt carries the
vibrations) up to ``LAST_FRACTION`` of the modes (the highest see the fitting and aliasing
errors): r0 in closed form for each L0 of ``L0_GRID``, L0 where the residual is least.  The
uncertainty of log r0 is the residual scatter over the square root of the modes used; L0's
the spread of the grid points within one unit of chi-squared of the best.

A record reads each variance low by about 1/N, N the record's length in the mode's
correlation times (the sample variance about the record's own mean; the lowest orders
decorrelate over ~D/v: ~1 s at 8 m/s).  From the variances of the record's two halves (read
low by ~2/N) and of the whole, per radial order: the variance corrected to first order,
2 whole - halves (Richardson), which the fit reads, and N = (2 - r)/(1 - r), r = halves/whole
(``record_length``).  L0 rests on the lowest orders' variances against the others': it is
stated only when the orders ``LOW_ORDERS`` span ``MIN_CORRELATION_TIMES`` or more; else the
seeing is fitted over the L0 grid all the same and L0 is not estimated.  L0's uncertainty
includes the low orders' variance over N correlation times (``_ratio_uncertainty``), mapped
through the low-to-high variance ratio that L0 sets (+-9 % from 20 to 30 m).  Measured on
simulated records (seeing 1.0", L0 25 m, 8 m/s): the disturbance of a 1 s record, seeing
0.885 -> 0.969 corrected, N ~ 6, L0 not estimated (12 m before); identification of a 16 s
record at R9.7, N ~ 51, seeing 1.008, L0 20 +- 5.4 m (20 +- 10 before).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import special

from .. import blas
from ..disturbance.modal_psd import radial_order
from ..optics.asm import ModalBasis, covariance_applied
from ..optics.atmosphere import LAMBDA_REF_M
from ..optics.pupil import LBT_DIAMETER_M, Pupil
from .plant import Turbulence

L0_GRID = (8.0, 12.0, 16.0, 20.0, 25.0, 30.0, 40.0, 50.0, 70.0, 100.0)
UNKNOWN_L0_M = 25.0  # stated (sigma inf) for a foreign basis, whose variances are Kolmogorov's
FIRST_MODE = 3
LAST_FRACTION = 0.5
LOW_ORDERS = (2, 4)  # radial orders whose variances against the others' carry L0
MIN_CORRELATION_TIMES = 20.0  # their variances read ~5 % low or less: L0 is stated
NM_PER_RAD = LAMBDA_REF_M * 1e9 / (2 * math.pi)
NOLL = special.gamma(29 / 6) * 0.448 / (2 * special.gamma(1 / 6))  # fixes the Tip variance 0.448 (D/r0)^(5/3)


@blas.on_one_thread
def basis_variances(basis: ModalBasis, pupil: Pupil, L0_values: Sequence[float]) -> np.ndarray:
    """(len(L0_values), n_modes) V_i(L0), rad^2 at 500 nm for r0 = 1 m: s_i^T C s_i / n_p^2."""
    shapes = basis.shapes(pupil)  # (n_valid, n_modes)
    n_p = shapes.shape[0]
    return np.array([np.einsum("pm,pm->m", c, shapes) / n_p**2 for c in covariance_applied(shapes, pupil, L0_values)])


def noll_variances(n_modes: int, diameter_m: float = LBT_DIAMETER_M) -> np.ndarray:
    """(1, n_modes) Zernike variances of each mode's radial order for r0 = 1 m (Kolmogorov)."""
    n = radial_order(np.arange(1, n_modes + 1))
    return (NOLL * (n + 1) * special.gamma(n - 5 / 6) / special.gamma(n + 23 / 6) * diameter_m ** (5 / 3))[None, :]


def _low_orders(n: np.ndarray) -> np.ndarray:
    """Which of the radial orders ``n`` are the orders ``LOW_ORDERS``."""
    return (n >= LOW_ORDERS[0]) & (n <= LOW_ORDERS[1])


_LOW = np.flatnonzero(_low_orders(radial_order(np.arange(1, 40)))) + 1
LOW_MODES = f"{_LOW.min()}-{_LOW.max()}"  # their modes, as numbered (mode 1 = Tip)


def record_length(whole: np.ndarray, halves: np.ndarray) -> tuple[np.ndarray, float]:
    """(each mode's variance corrected for the record's length, N of the orders
    ``LOW_ORDERS``) from the variances of the whole record and the mean of its halves' (see the
    module).  The correction is per radial order, between 1 (a record never reads high) and 2."""
    n = radial_order(np.arange(1, len(whole) + 1))
    corrected = np.array(whole, dtype=float)
    for order in np.unique(n):
        k = n == order
        w, h = float(np.sum(whole[k])), float(np.sum(halves[k]))
        if w > 0:
            corrected[k] *= min(2.0, max(1.0, (2 * w - h) / w))
    low = _low_orders(n)
    w, h = float(np.sum(whole[low])), float(np.sum(halves[low]))
    r = h / w if w > 0 else 0.0
    return corrected, (math.inf if r >= 1 else max(0.0, (2 - r) / (1 - r)))


def _low_to_high(variances: np.ndarray, modes: np.ndarray) -> np.ndarray:
    """Per L0 of the table, the summed variance of the orders ``LOW_ORDERS`` over the other
    fitted modes': the shape L0 sets."""
    low = _low_orders(radial_order(modes + 1))
    return variances[:, modes[low]].sum(axis=1) / np.maximum(variances[:, modes[~low]].sum(axis=1), 1e-300)


def _L0_interval(variances: np.ndarray, modes: np.ndarray, best: int, L0_values: Sequence[float], spread: float) -> list[float]:
    """The L0s whose low-to-high variance ratio is within ``spread`` (relative) of the best
    one's, interpolated in log-log between the grid's points (the ratio grows with L0)."""
    if spread <= 0:
        return []
    ratio = np.log(_low_to_high(variances, modes))
    logs = np.log(np.asarray(L0_values, dtype=float))
    return [float(np.exp(np.interp(ratio[best] + s, ratio, logs))) for s in (-spread, spread)]


def _ratio_uncertainty(correlation_times: float) -> float:
    """Relative uncertainty of the low orders' variance from a record of ``correlation_times``:
    the first-order bias the correction removes (1/N, kept as a systematic) and the scatter of
    a variance over N correlation times, sqrt(2/N), pooled over the low orders (not over their
    modes: the modes of one order see the same eddies pass, their errors are not independent)."""
    if not math.isfinite(correlation_times):
        return 0.0
    N = max(correlation_times, 1.0)
    return math.hypot(1 / N, math.sqrt(2 / ((LOW_ORDERS[1] - LOW_ORDERS[0] + 1) * N)))


def fit_turbulence(
    pol_variance_nm2: np.ndarray, variances: np.ndarray, L0_values: Sequence[float], correlation_times: float = math.inf
) -> Turbulence:
    """r0 and L0 (see the module) from each mode's pseudo-open-loop variance (nm^2, noise
    removed) and the (L0, mode) table of V_i; L0's uncertainty includes the low orders'
    variance over a record of ``correlation_times`` (``record_length``)."""
    n_modes = len(pol_variance_nm2)
    modes = np.arange(FIRST_MODE - 1, max(FIRST_MODE, int(LAST_FRACTION * n_modes)))
    v = pol_variance_nm2[modes] / NM_PER_RAD**2
    ok = v > 0
    logs = np.log(v[ok])
    fits = []
    for V in variances:
        r = logs - np.log(V[modes][ok])
        a = float(np.mean(r))
        fits.append((float(np.sum((r - a) ** 2)), a, float(np.std(r))))
    costs = np.array([c for c, _, _ in fits])
    best = int(np.argmin(costs))
    _, a, scatter = fits[best]
    r0 = math.exp(-0.6 * a)  # a = log r0^(-5/3)
    sigma_log_r0 = 0.6 * scatter / math.sqrt(max(1, ok.sum()))
    seeing = 0.98 * LAMBDA_REF_M / r0 * 180 / math.pi * 3600
    L0 = float(L0_values[best])
    if len(L0_values) > 1:
        scale = costs[best] / max(1, ok.sum() - 2)  # chi^2 per degree of freedom of the log fit
        near = [x for x, c in zip(L0_values, costs) if c - costs[best] <= scale]
        near += _L0_interval(variances, modes, best, L0_values, _ratio_uncertainty(correlation_times))
        L0_sigma = 0.5 * (max(near) - min(near)) if max(near) > min(near) else 0.5 * L0
    else:
        L0_sigma = math.inf
    return Turbulence(seeing, seeing * sigma_log_r0, L0, L0_sigma)
