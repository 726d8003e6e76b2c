"""The WFS detector: photons on the pupil images -> a frame in electrons (float32).

SOUL's WFS camera is the First Light Imaging OCAM2K (e2v CCD220 EMCCD, 240 x 240 pixels):
at its high electron-multiplying gain the read-out noise referred to the input is below
0.2 e- RMS, and the multiplication adds an excess noise factor F = sqrt(2) (F^2 = 2) on the
photo-electrons (Feautrier et al. 2011; Arcetri semi-analytic error budget).

Noise model of one frame (all per pixel, in input electrons):

* photo-electrons and background: Poisson(lambda), lambda = photons x (intensity) + background;
* EM register (when ``excess_noise``): the output of n input electrons is Gamma(n, 1) (the
  high-gain limit of the multiplication chain, gain divided out), so the variance becomes
  F^2 lambda = 2 lambda; without it (a CCD), the Poisson count as it is;
* read-out noise: Gaussian, ``read_noise_e`` RMS.

The background (sky + dark) is 0 by default: an R-band sky of ~20.8 mag/arcsec^2 gives
~1e-4 photons per pixel per frame at 1.7 kHz on SOUL's 2.1" field, negligible next to a
guide star.  The mean background is known to the RTC and subtracted by the slope computer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError


@dataclass(frozen=True)
class Detector:
    read_noise_e: float = 0.2
    excess_noise: bool = True
    background_e: float = 0.0

    def __post_init__(self):
        if not (math.isfinite(self.read_noise_e) and 0 <= self.read_noise_e <= 1000):
            raise InputError(f"read-out noise must be in 0..1000 e- RMS, got {self.read_noise_e}")
        if not (math.isfinite(self.background_e) and 0 <= self.background_e <= 1e6):
            raise InputError(f"background must be in 0..1e6 e- per pixel per frame, got {self.background_e}")

    @property
    def excess_noise_factor_squared(self) -> float:
        return 2.0 if self.excess_noise else 1.0

    def expected(self, intensity: np.ndarray, photons: float) -> np.ndarray:
        """The noiseless frame: mean electrons per pixel."""
        return (np.asarray(intensity, dtype=np.float32) * np.float32(photons) + np.float32(self.background_e)).astype(np.float32)

    def read(self, intensity: np.ndarray, photons: float, rng: np.random.Generator) -> np.ndarray:
        """One noisy frame (float32 electrons) for an intensity map normalised to a total of 1
        for the whole beam, and ``photons`` detected photons in the whole beam per frame."""
        mean = np.asarray(intensity, dtype=np.float64) * photons + self.background_e
        electrons = rng.poisson(np.maximum(mean, 0.0)).astype(np.float64)
        if self.excess_noise:
            lit = electrons > 0
            electrons[lit] = rng.gamma(electrons[lit], 1.0)
        if self.read_noise_e > 0:
            electrons += rng.normal(0.0, self.read_noise_e, size=electrons.shape)
        return electrons.astype(np.float32)

    def background_frame(self, shape: tuple[int, int]) -> np.ndarray:
        return np.full(shape, self.background_e, dtype=np.float32)
