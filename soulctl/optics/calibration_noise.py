"""The interaction matrix as measured at a finite flux: the calibration error of noise.

``calibration.calibrate`` measures D with noiseless frames, what a bright calibration source
and long averaging approach (SOUL calibrates the ASM on a fibre in daytime).  Measured at
``photons_per_frame`` of the source in the beam, through the loop's detector (photon noise,
EMCCD excess noise, read noise), with ``frames`` frames averaged per push and per pull, each
column carries noise of variance sigma_s^2 / (2 frames a^2) per slope (sigma_s the slopes'
noise per frame, a the push): D = D_0 + N.  The loop then runs with R = D^+ of that D, while
the modes that measure it stay the calibration's.  The optics are propagated once per push
(no turbulence during a calibration); only the detector reads repeat.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..ranges import CALIBRATION_FRAMES, CALIBRATION_PHOTONS, SEED
from .calibration import Calibration, mode_maps, push_pull
from .detector import Detector
from .pwfs import Pyramid
from .sensor import WavefrontSensor


@dataclass(frozen=True, kw_only=True)
class CalibrationNoise:
    photons_per_frame: float = 0.0  # of the calibration source in the whole beam; 0: noiseless
    frames: int = 1  # averaged per push and per pull
    seed: int = 1  # the calibration's own noise draw

    def __post_init__(self):
        if self.photons_per_frame != 0:
            CALIBRATION_PHOTONS.check(self.photons_per_frame, "calibration.photons_per_frame")
        CALIBRATION_FRAMES.check(self.frames, "calibration.frames")
        SEED.check(self.seed, "calibration.seed")

    @property
    def active(self) -> bool:
        return self.photons_per_frame > 0


def averaged_slopes(sensor: WavefrontSensor, opd_nm: np.ndarray, frames: int, rng: np.random.Generator) -> np.ndarray:
    """(n_maps, n_slopes): for each OPD map of the stack, the mean slopes of ``frames`` noisy
    reads of its intensity (the optics propagated once)."""
    out = np.zeros((opd_nm.shape[0], sensor.n_slopes))
    for i, intensity in enumerate(sensor.pyramid.intensity(np.asarray(opd_nm, dtype=np.float32))):
        for _ in range(frames):
            out[i] += sensor.slopes_of_frame(sensor.detector.read(intensity, sensor.photons_per_frame, rng))
    return out / frames


def measured_calibration(calibration: Calibration, noise: CalibrationNoise, detector: Detector = Detector()) -> Calibration:
    """``calibration`` with D measured at ``noise``'s flux and R = D^+ of it."""
    sensor = WavefrontSensor(Pyramid(calibration.setup.pyramid), detector, noise.photons_per_frame)
    maps = mode_maps(calibration.basis.shapes(sensor.pupil), sensor.pupil)
    rng = np.random.default_rng(noise.seed)
    D = push_pull(sensor, maps, calibration.setup.push_nm, slopes_of=lambda opd: averaged_slopes(sensor, opd, noise.frames, rng))
    return dataclasses.replace(calibration, interaction_matrix=D, reconstructor=np.linalg.pinv(D), from_cache=False)
