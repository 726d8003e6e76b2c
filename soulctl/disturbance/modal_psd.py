"""A model of the temporal PSD of each mode of the turbulence, for the optimisers' initial gains.

For a frozen-flow layer of speed V over a pupil of diameter D, the PSD of a mode of radial
order n is flat below the cut-off f_c = 0.3 (n + 1) V / D and falls as f^(-17/3) above it
(Conan, Rousset & Madec 1995, JOSA A 12, 1559, Sec. 4).  Here one smooth form joins the two,

    Phi(f) = sigma^2 / (f_c I) / (1 + (f / f_c)^(17/3)),   I = (pi / a) / sin(pi / a), a = 17 / 3,

normalised to the mode's variance sigma^2 over 0..infinity (one-sided).  The radial order of a
KL mode is that of the Zernike polynomial of the same rank (Noll's j = mode + 1, piston being
j = 1): KL modes are ordered by variance as the Zernike radial orders are.  Tip/Tilt's f^(-2/3)
slope below its cut-off is left out (``turbulence.TurbulenceTipTilt`` has the exact Tip/Tilt
PSD); this model only sets starting gains.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError

SLOPE = 17.0 / 3.0
_NORM = (math.pi / SLOPE) / math.sin(math.pi / SLOPE)  # integral of 1 / (1 + x^a) over 0..inf
CUTOFF_PER_ORDER = 0.3  # f_c = 0.3 (n + 1) V / D


def radial_order(mode) -> np.ndarray:
    """Radial order n of the 1-based mode index without piston (1, 2: Tip/Tilt, n = 1)."""
    j = np.asarray(mode, dtype=float) + 1.0
    if np.any(j < 2):
        raise InputError("mode indices start at 1 (Tip)")
    return np.ceil((np.sqrt(8.0 * j + 1.0) - 3.0) / 2.0 - 1e-12)


def cutoff_hz(mode, wind_m_s: float, diameter_m: float) -> np.ndarray:
    """f_c = 0.3 (n + 1) V / D of each mode."""
    return CUTOFF_PER_ORDER * (radial_order(mode) + 1.0) * wind_m_s / diameter_m


def modal_psd(f, variance, cutoff) -> np.ndarray:
    """Phi_i(f) (variance units / Hz), (n_modes, F), of the module's model."""
    f = np.asarray(f, dtype=float)[None, :]
    fc = np.asarray(cutoff, dtype=float)[:, None]
    return np.asarray(variance, dtype=float)[:, None] / (fc * _NORM) / (1.0 + (f / fc) ** SLOPE)
