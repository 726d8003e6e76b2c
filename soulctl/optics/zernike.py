"""Zernike polynomials with Noll's (1976) ordering and normalisation, sampled on a pixel grid.

Noll, J. Opt. Soc. Am. 66, 207 (1976): j = 1 piston, 2 tip (x), 3 tilt (y), 4 focus, ...;
even j carry cos(m theta), odd j sin(m theta); Z_j = sqrt(n+1) R_n^m (m = 0) or
sqrt(2(n+1)) R_n^m cos/sin(m theta).  Sampling as in ``soulctl.optics.pupil``: pixel centres at
(i + 0.5 - n/2) pixels from the centre, x along columns, y along rows, the pupil a disc of
n pixels across.
"""

from __future__ import annotations

from math import factorial

import numpy as np

from ..errors import InputError


def noll_to_nm(j: int) -> tuple[int, int]:
    """Radial order n and azimuthal order m of Noll index j >= 1; m > 0 is cos, m < 0 sin."""
    if int(j) != j or j < 1:
        raise InputError(f"Noll index must be an integer >= 1, got {j}")
    j = int(j)
    n, rest = 0, j - 1
    while rest > n:
        n += 1
        rest -= n
    m = (n % 2) + 2 * ((rest + ((n + 1) % 2)) // 2)
    return n, (m if j % 2 == 0 or m == 0 else -m)


def pupil_mask(n_pixels: int, obstruction: float = 0.0) -> np.ndarray:
    """Boolean mask of the pixel centres inside the (annular) disc of n_pixels across."""
    rho, _ = _polar(n_pixels)
    return (rho <= 1.0) & (rho >= obstruction)


def zernike(j: int, n_pixels: int, obstruction: float = 0.0) -> np.ndarray:
    """Z_j on an n_pixels x n_pixels grid, zero outside the pupil, unit RMS over the pupil
    pixels (renormalised on the samples; not re-orthogonalised on an obstructed pupil)."""
    if int(n_pixels) != n_pixels or n_pixels < 2:
        raise InputError(f"Zernike sampling must be an integer >= 2 pixels, got {n_pixels}")
    if not (0.0 <= obstruction < 1.0):
        raise InputError(f"central obstruction must be in [0, 1), got {obstruction}")
    n, m = noll_to_nm(j)
    rho, theta = _polar(int(n_pixels))
    mask = (rho <= 1.0) & (rho >= obstruction)
    radial = np.zeros_like(rho)
    for s in range((n - abs(m)) // 2 + 1):
        c = (-1) ** s * factorial(n - s) / (factorial(s) * factorial((n + abs(m)) // 2 - s) * factorial((n - abs(m)) // 2 - s))
        radial += c * rho ** (n - 2 * s)
    if m == 0:
        z = radial
    elif m > 0:
        z = radial * np.cos(m * theta)
    else:
        z = radial * np.sin(-m * theta)
    z = np.where(mask, z, 0.0)
    return z / np.sqrt(np.mean(z[mask] ** 2))


def _polar(n: int) -> tuple[np.ndarray, np.ndarray]:
    c = (np.arange(n) + 0.5 - n / 2) / (n / 2)
    x, y = np.meshgrid(c, c)
    return np.hypot(x, y), np.arctan2(y, x)
