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
"""

from __future__ import annotations

import math

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
NM_PER_RAD = LAMBDA_REF_M * 1e9 / (2 * math.pi)
NOLL = special.gamma(29 / 6) * 0.448 / (2 * special.gamma(1 / 6))  # fixes the Tip variance 0.448 (D/r0)^(5/3)


@blas.on_one_thread
def basis_variances(basis: ModalBasis, pupil: Pupil, L0_values) -> np.ndarray:
    """(len(L0_values), n_modes) V_i(L0), rad^2 at 500 nm for r0 = 1 m: s_i^T C s_i / n_p^2."""
    shapes = basis.shapes(pupil)  # (n_valid, n_modes)
    n_p = shapes.shape[0]
    return np.array([np.einsum("pm,pm->m", c, shapes) / n_p**2 for c in covariance_applied(shapes, pupil, L0_values)])


def noll_variances(n_modes: int, diameter_m: float = LBT_DIAMETER_M) -> np.ndarray:
    """(1, n_modes) Zernike variances of each mode's radial order for r0 = 1 m (Kolmogorov)."""
    n = radial_order(np.arange(1, n_modes + 1))
    return (NOLL * (n + 1) * special.gamma(n - 5 / 6) / special.gamma(n + 23 / 6) * diameter_m ** (5 / 3))[None, :]


def fit_turbulence(pol_variance_nm2: np.ndarray, variances: np.ndarray, L0_values) -> Turbulence:
    """r0 and L0 (see the module) from each mode's pseudo-open-loop variance (nm^2, noise
    removed) and the (L0, mode) table of V_i."""
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
        L0_sigma = 0.5 * (max(near) - min(near)) if len(near) > 1 else 0.5 * L0
    else:
        L0_sigma = math.inf
    return Turbulence(seeing, seeing * sigma_log_r0, L0, L0_sigma)
