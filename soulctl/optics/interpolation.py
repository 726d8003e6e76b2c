"""Sub-pixel translation of periodic screens without smoothing: the frozen flow's interpolation.

A screen sampled at dx holds frequencies up to 1/(2 dx).  Interpolating it at a fractional
offset f with a short kernel on its own grid low-passes it by the kernel's response there
(bilinear: cos(pi f nu dx)-like, 14 % of the 500-mode fitting error at half a pixel; quintic
B-splines 1.5-2 %), so a moving screen's statistics would change with the wind's sub-pixel
phase.  Here the screen's Fourier series is evaluated once on a grid ``UPSAMPLING`` times finer
(exact band-limited interpolation, no new frequency), where every frequency the screen holds is
below half the fine Nyquist and cubic B-splines (Unser, IEEE Signal Process. Mag. 16, 22, 1999)
interpolate it to within 0.2 % of the fitting error of an exact Fourier shift.  The spline
prefilter is folded into the same Fourier pass.  A translation is separable: 4 + 4 weighted,
strided row and column sums per layer and frame.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import scipy.fft
from scipy import special


def separable_sums(window: np.ndarray, wy: np.ndarray, wx: np.ndarray, stride: int, n: int) -> np.ndarray:
    """sum_ij wy_i wx_j window[i + stride r, j + stride c] for r, c < n, in the window's
    precision, in place (the frame's hot path)."""
    wy, wx = wy.astype(window.dtype), wx.astype(window.dtype)
    span = stride * n
    rows = window[0:span:stride] * wy[0]
    for j in range(1, len(wy)):
        rows += window[j : j + span : stride] * wy[j]
    out = rows[:, 0:span:stride] * wx[0]
    for j in range(1, len(wx)):
        out += rows[:, j : j + span : stride] * wx[j]
    return out


SPLINE_ORDER = 3  # the frozen-flow interpolation: cubic B-splines (4 taps per axis; fine_spline_coefficients) ...
UPSAMPLING = 2  # ... on the screen band-limited to twice its sampling (docs/physics.md)


def _fine_spectrum(screen: np.ndarray, factor: int) -> np.ndarray:
    """rfft2 of the periodic ``screen`` (ny x nx, both even) zero-padded to factor ny x factor
    nx, the Nyquist row and column split between +n/2 and -n/2, scaled so that irfft2
    interpolates."""
    ny, nx = screen.shape
    hy, hx, My, Mx = ny // 2, nx // 2, factor * ny, factor * nx
    F = scipy.fft.rfft2(screen, workers=-1) * factor**2  # (ny, hx + 1)
    G = np.zeros((My, Mx // 2 + 1), dtype=F.dtype)
    G[:hy, : hx + 1] = F[:hy]
    G[My - hy + 1 :, : hx + 1] = F[hy + 1 :]
    G[hy, : hx + 1] = G[My - hy, : hx + 1] = 0.5 * F[hy]
    G[:, hx] *= 0.5  # irfft2 counts column hx of the finer grid as +hx and -hx
    return G


def band_limited_upsample(screen: np.ndarray, factor: int = UPSAMPLING) -> np.ndarray:
    """The periodic ``screen`` on a grid ``factor`` times finer: its Fourier series evaluated
    there.  It passes through every sample of ``screen`` and adds no frequency above the
    screen's Nyquist."""
    shape = (factor * screen.shape[0], factor * screen.shape[1])
    return scipy.fft.irfft2(_fine_spectrum(screen, factor), s=shape)


def fine_spline_coefficients(screen: np.ndarray, factor: int = UPSAMPLING, pad: int = 0) -> np.ndarray:
    """Periodic cubic B-spline coefficients of ``band_limited_upsample(screen)`` (what
    ``scipy.ndimage.spline_filter(..., order=3, mode='grid-wrap')`` gives), in the same Fourier
    pass: the spectrum divided by the sampled cubic B-spline's, (4 + 2 cos 2 pi nu) / 6 per axis.
    In float32, the precision the frozen flow stores them in (relative error ~2e-7; 2.5x
    faster than float64 on the loop's 1024-2048 px screens), on all cores (set-up only).
    ``pad``: the result wrapped ``pad`` samples further along both axes (``np.pad(...,
    (0, pad), mode='wrap')``).  irfft2's two passes are made by hand, the first in place and the
    second by blocks of rows into the padded result, so that a long screen's set-up holds two
    fine grids rather than four (the same numbers as ``scipy.fft.irfft2``)."""
    My, Mx = factor * screen.shape[0], factor * screen.shape[1]
    b = lambda nu: ((4.0 + 2.0 * np.cos(2.0 * np.pi * nu)) / 6.0).astype(np.float32)  # noqa: E731
    G = _fine_spectrum(np.asarray(screen, dtype=np.float32), factor)
    G /= b(np.fft.fftfreq(My))[:, None] * b(np.fft.rfftfreq(Mx))[None, :]
    G = scipy.fft.ifft(G, axis=0, overwrite_x=True, workers=-1)
    out = np.empty((My + pad, Mx + pad), dtype=np.float32)
    for r in range(0, My, _ROW_BLOCK):
        out[r : min(r + _ROW_BLOCK, My), :Mx] = scipy.fft.irfft(G[r : r + _ROW_BLOCK], n=Mx, axis=1, workers=-1)
    del G
    for start in range(Mx, Mx + pad, Mx):  # wrap: column j is column j mod Mx, then row i is row i mod My
        out[:My, start : start + Mx] = out[:My, : min(Mx, Mx + pad - start)]
    for start in range(My, My + pad, My):
        out[start : start + My] = out[: min(My, My + pad - start)]
    return out


_ROW_BLOCK = 256  # rows per block of the inverse transform's second pass


@functools.lru_cache(maxsize=8)
def _bspline_terms(order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    m = order + 1
    j = np.arange(-(order // 2), order - order // 2 + 1)
    k = np.arange(m + 1)
    return m / 2.0 - j, k, (-1.0) ** k * special.comb(m, k) / math.factorial(order)


def bspline_weights(f: float, order: int = SPLINE_ORDER) -> np.ndarray:
    """The ``order + 1`` weights beta_order(f - j), j = -(order // 2) .. order - order // 2, of
    the B-spline coefficients around a point at fraction f in [0, 1) past a sample (the
    cardinal B-spline in closed form: sum_k (-1)^k C(m, k) (x + m/2 - k)_+^(m-1) / (m-1)!)."""
    offset, k, c = _bspline_terms(order)
    x = np.maximum((f + offset)[:, None] - k[None, :], 0.0)
    return (x**order) @ c
