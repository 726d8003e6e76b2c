"""The measurement chain of one frame: wavefront -> PWFS optics -> detector -> slopes.

Slopes come out of the C++ slope computer (``soulctl._core.SlopeComputer``) from the simulated
frame, the code path a real frame takes: the detector's mean background is subtracted, the
four pupil images are combined with the global normalisation, and the reference slopes (those
of the unaberrated beam) are subtracted.
"""

from __future__ import annotations

import math

import numpy as np

from .._core import SlopeComputer
from ..errors import InputError
from .detector import Detector
from .photometry import WfsPhotometry
from .pwfs import Pyramid


def photons_in_beam(photometry: WfsPhotometry, magnitude_r: float, frame_rate_hz: float, pupil_area_m2: float) -> float:
    """Detected photons per frame in the whole beam (all four pupil images), with the zero point
    and throughput that ``configure`` uses for its photons per sub-aperture."""
    return photometry.zero_point_ph_s_m2 * pupil_area_m2 * 10.0 ** (-0.4 * magnitude_r) / frame_rate_hz


class WavefrontSensor:
    def __init__(self, pyramid: Pyramid, detector: Detector, photons_per_frame: float, normalization: str = "global"):
        if not (math.isfinite(photons_per_frame) and photons_per_frame > 0):
            raise InputError(f"photons per frame must be a positive number, got {photons_per_frame}")
        self.pyramid = pyramid
        self.detector = detector
        self.photons_per_frame = float(photons_per_frame)
        shape = pyramid.config.frame_shape
        self.slope_computer = SlopeComputer(pyramid.subaperture_pixels, shape, normalization)
        if detector.background_e > 0:
            self.slope_computer.set_background(detector.background_frame(shape))
        self.reference_slopes = self.slope_computer.compute(self.expected_frame_of(pyramid.reference_intensity)).copy()
        self.slope_computer.set_reference(self.reference_slopes)

    @property
    def n_slopes(self) -> int:
        return 2 * self.slope_computer.n_subapertures

    @property
    def n_subapertures(self) -> int:
        return self.slope_computer.n_subapertures

    @property
    def pupil(self):
        return self.pyramid.pupil

    def expected_frame_of(self, intensity: np.ndarray) -> np.ndarray:
        return self.detector.expected(intensity, self.photons_per_frame)

    def frame(self, opd_nm: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """The detector frame (float32 electrons) for one OPD map: noisy with ``rng``, else the
        noiseless mean."""
        intensity = self.pyramid.intensity(opd_nm)
        if rng is None:
            return self.expected_frame_of(intensity)
        return self.detector.read(intensity, self.photons_per_frame, rng)

    def slopes_of_frame(self, frame: np.ndarray) -> np.ndarray:
        return self.slope_computer.compute(np.ascontiguousarray(frame, dtype=np.float32)).copy()

    def slopes(self, opd_nm: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """Slopes [sx..., sy...] (float32) of one OPD map (see :meth:`frame`)."""
        return self.slopes_of_frame(self.frame(opd_nm, rng))

    def noiseless_slopes(self, opd_nm: np.ndarray, batch: int = 16) -> np.ndarray:
        """(n_maps, n_slopes) noiseless slopes of a stack of OPD maps, computed in batches."""
        opd_nm = np.asarray(opd_nm, dtype=np.float32)
        out = np.empty((opd_nm.shape[0], self.n_slopes), dtype=np.float64)
        for start in range(0, opd_nm.shape[0], batch):
            frames = self.pyramid.intensity(opd_nm[start : start + batch])
            for i, intensity in enumerate(frames):
                out[start + i] = self.slope_computer.compute(self.expected_frame_of(intensity))
        return out

    def modal_noise_nm(self, reconstructor: np.ndarray, frames: int = 256, seed: int = 0) -> np.ndarray:
        """Per mode, the RMS (nm) of R s over ``frames`` noisy reads of the unaberrated frame:
        the detector's noise (photons, read-out, excess factor) propagated through the
        reconstructor at k = 1.  Its own generator (``seed``), so that it draws nothing from a
        loop's.  Around a partly corrected wavefront the flux per pixel, hence the noise, is
        much the same (the modulation spreads the light)."""
        rng = np.random.default_rng(seed)
        intensity = self.pyramid.reference_intensity
        s = np.stack([self.slopes_of_frame(self.detector.read(intensity, self.photons_per_frame, rng)) for _ in range(frames)])
        modes = s.astype(np.float64) @ np.asarray(reconstructor, dtype=np.float64).T
        return modes.std(axis=0)
