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
from .calibration import Calibration, mode_maps
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


def averaged_slopes(sensor: WavefrontSensor, intensity: np.ndarray, frames: int, rng: np.random.Generator) -> np.ndarray:
    """The mean slopes of ``frames`` noisy reads of one intensity map."""
    total = np.zeros(sensor.n_slopes)
    for _ in range(frames):
        total += sensor.slopes_of_frame(sensor.detector.read(intensity, sensor.photons_per_frame, rng))
    return total / frames


def noisy_push_pull(sensor: WavefrontSensor, maps: np.ndarray, push_nm: float, frames: int, rng: np.random.Generator) -> np.ndarray:
    """(n_slopes, n_maps): D by push-pull around the unaberrated beam, each push and pull the
    mean of ``frames`` noisy frames."""
    out = np.empty((sensor.n_slopes, maps.shape[0]))
    chunk = 8
    for start in range(0, maps.shape[0], chunk):
        m = maps[start : start + chunk] * np.float32(push_nm)
        intensities = sensor.pyramid.intensity(np.concatenate([m, -m]))
        k = m.shape[0]
        for i in range(k):
            plus = averaged_slopes(sensor, intensities[i], frames, rng)
            minus = averaged_slopes(sensor, intensities[k + i], frames, rng)
            out[:, start + i] = (plus - minus) / (2 * push_nm)
    return out


def measured_calibration(calibration: Calibration, noise: CalibrationNoise, detector: Detector = Detector()) -> Calibration:
    """``calibration`` with D measured at ``noise``'s flux and R = D^+ of it."""
    sensor = WavefrontSensor(Pyramid(calibration.setup.pyramid), detector, noise.photons_per_frame)
    maps = mode_maps(calibration.basis.shapes(sensor.pupil), sensor.pupil)
    D = noisy_push_pull(sensor, maps, calibration.setup.push_nm, noise.frames, np.random.default_rng(noise.seed))
    return dataclasses.replace(calibration, interaction_matrix=D, reconstructor=np.linalg.pinv(D), from_cache=False)
