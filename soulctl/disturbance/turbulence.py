"""Temporal PSD of the turbulent Tip/Tilt on the sky (von Kármán, one frozen-flow layer).

Model (Conan, Rousset & Madec 1995, JOSA A 12, 1559; Noll 1976):

* phase PSD at 500 nm, W(k) = 0.0229 r0^(-5/3) (k^2 + 1/L0^2)^(-11/6)  [rad^2 m^2], k in cycles/m,
  r0 = 0.98 * 500 nm / seeing;
* Zernike tilt (Noll Z2, Z3) of a filled circular pupil of diameter D: its filter is
  |Q(k, phi)|^2 = 16 [J2(pi k D) / (pi k D)]^2 cos^2(phi)  (sin^2 for the other axis);
* one layer moving at V along x: PSD(f) = (2/V) * integral over k_y of W |Q|^2 at k_x = f/V
  (one-sided in f), for the Zernike coefficient in rad^2/Hz;
* angle on the sky: theta = (lambda / 2 pi) * 4 a / D for a coefficient a in rad at lambda
  (achromatic), so the PSD is returned in mas^2/Hz.

"Per axis" below is the mean of the axis along the wind and the axis across it, the input a
single Tip/Tilt filter sees when it controls both.  Limits: one equivalent layer (the wind
speed is the turbulence-weighted one), no central obstruction (it changes the tilt variance by
a few per cent for the LBT's 11 %), Z-tilt rather than G-tilt, no aliasing above Nyquist.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import jv

from .. import defaults
from ..errors import InputError
from ..optics.atmosphere import LAMBDA_REF_M, phase_psd_k2, r0_from_seeing
from ..optics.pupil import LBT_DIAMETER_M, MAS_PER_RAD  # the pupil conjugated to the ASM (LBTO elab_lib)
from ..ranges import SEEING_ARCSEC


@dataclass(frozen=True)
class TurbulenceTipTilt:
    seeing_arcsec: float = defaults.SEEING_ARCSEC
    outer_scale_m: float = defaults.L0_M
    wind_speed_m_s: float = defaults.WIND_M_S
    diameter_m: float = LBT_DIAMETER_M

    def __post_init__(self):
        SEEING_ARCSEC.check(self.seeing_arcsec, "seeing")
        checks = (
            ("outer scale L0", self.outer_scale_m, 0.5, 1e12, "m"),
            ("wind speed", self.wind_speed_m_s, 0.1, 100.0, "m/s"),
            ("diameter", self.diameter_m, 0.1, 100.0, "m"),
        )
        for name, value, lo, hi, unit in checks:
            if not (lo <= value <= hi):
                raise InputError(f"{name} must be in {lo:g}..{hi:g} {unit}, got {value:g}")

    @property
    def r0_m(self) -> float:
        return r0_from_seeing(self.seeing_arcsec)

    def _phase_psd(self, k2: np.ndarray) -> np.ndarray:
        return phase_psd_k2(k2, self.r0_m, self.outer_scale_m)

    def _tilt_filter(self, k: np.ndarray) -> np.ndarray:
        """16 [J2(pi k D)/(pi k D)]^2, the azimuthal factor (cos^2 or sin^2) left out."""
        x = np.pi * k * self.diameter_m
        with np.errstate(invalid="ignore", divide="ignore"):
            q = np.where(x > 1e-8, jv(2, x) / x, x / 8.0)
        return 16.0 * q**2

    def _coefficient_to_mas2(self) -> float:
        return (LAMBDA_REF_M / (2 * math.pi) * 4.0 / self.diameter_m * MAS_PER_RAD) ** 2

    def psd(self, f_hz, axis: str = "mean") -> np.ndarray:
        """One-sided temporal PSD (mas^2/Hz) of the Tip/Tilt angle; axis 'along' (the wind),
        'across', or 'mean' of the two."""
        if axis not in ("along", "across", "mean"):
            raise InputError(f"axis must be 'along', 'across' or 'mean', got '{axis}'")
        f = np.atleast_1d(np.asarray(f_hz, dtype=float))
        V, D = self.wind_speed_m_s, self.diameter_m
        ky = np.concatenate([[0.0], np.geomspace(1e-4 / D, 60.0 / D, 400)])
        kx = (f / V)[:, None]
        k2 = kx**2 + ky[None, :] ** 2
        base = self._phase_psd(k2) * self._tilt_filter(np.sqrt(k2))
        with np.errstate(invalid="ignore", divide="ignore"):
            cos2 = np.where(k2 > 0, kx**2 / k2, 0.5)
        azimuth = {"along": cos2, "across": 1.0 - cos2, "mean": 0.5}[axis]
        integral = np.trapezoid(base * azimuth, ky, axis=1)  # over k_y >= 0: half the line
        return (2.0 * 2.0 / V) * integral * self._coefficient_to_mas2()

    def variance_mas2(self, axis: str = "mean") -> float:
        """Tip/Tilt angle variance per axis (mas^2) from the 2-D spatial integral (not the
        temporal PSD): the reference the PSD integrates to."""
        k = np.concatenate([[0.0], np.geomspace(1e-8 / self.diameter_m, 200.0 / self.diameter_m, 20000)])
        # The azimuthal mean of cos^2 is 1/2 for both axes: 2 pi k dk * 1/2.
        radial = self._phase_psd(k**2) * self._tilt_filter(k) * np.pi * k
        return float(np.trapezoid(radial, k)) * self._coefficient_to_mas2()
