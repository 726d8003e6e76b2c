"""The interaction matrix as measured: the calibration errors of noise and of the residual.

``calibration.calibrate`` measures D with noiseless frames on an unaberrated beam, what a
bright calibration source and long averaging approach (SOUL calibrates the ASM on a fibre in
daytime).  Two ways a measured D departs from it:

* **Noise.** Measured at ``photons_per_frame`` of the source in the beam, through the loop's
  detector (photon noise, EMCCD excess noise, read noise), with ``frames`` frames averaged per
  push and per pull, each column carries noise of variance sigma_s^2 / (2 frames a^2) per slope
  (sigma_s the slopes' noise per frame, a the push): D = D_0 + N.  The optics are propagated
  once per push; only the detector reads repeat.
* **Another optical gain.** Measured around a residual phase (``seeing_arcsec`` > 0: on sky,
  or with turbulence injected on the ASM), the pyramid answers each push with its optical gain
  there: D ~ D_0 diag(gamma(seeing)) (optics.optical_gains).  D is the mean of the push-pull
  responses around ``SCREENS`` residual realisations of ``optics.optical_gains.residual_screens``
  at that seeing (the fitting error plus 10 % of the controlled modes).  A loop whose residual
  is that one then has the effective optical gain 1; at another seeing, gamma_loop / gamma_cal.

The loop runs with R = D^+ of the measured D, while the modes that measure it stay the
calibration's.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .. import blas, defaults
from ..ranges import CALIBRATION_FRAMES, CALIBRATION_PHOTONS, SEED, SEEING_ARCSEC
from .calibration import Calibration, calibration_sensor, mode_maps, push_pull
from .detector import Detector
from .optical_gains import SCREENS, CorrectionLevel, residual_screens
from .pwfs import Pyramid
from .sensor import WavefrontSensor


@dataclass(frozen=True, kw_only=True)
class CalibrationNoise:
    photons_per_frame: float = 0.0  # of the calibration source in the whole beam; 0: noiseless
    frames: int = 1  # averaged per push and per pull
    seed: int = 1  # the calibration's own noise draw and residual realisations
    seeing_arcsec: float = 0.0  # the residual's seeing the matrix is measured around; 0: none (a fibre)

    def __post_init__(self):
        if self.photons_per_frame != 0:
            CALIBRATION_PHOTONS.check(self.photons_per_frame, "calibration.photons_per_frame")
        CALIBRATION_FRAMES.check(self.frames, "calibration.frames")
        SEED.check(self.seed, "calibration.seed")
        if self.seeing_arcsec != 0:
            SEEING_ARCSEC.check(self.seeing_arcsec, "calibration.seeing_arcsec (0: no residual)")

    @property
    def active(self) -> bool:
        return self.photons_per_frame > 0 or self.seeing_arcsec > 0


def averaged_slopes(sensor: WavefrontSensor, opd_nm: np.ndarray, frames: int, rng: np.random.Generator) -> np.ndarray:
    """(n_maps, n_slopes): for each OPD map of the stack, the mean slopes of ``frames`` noisy
    reads of its intensity (the optics propagated once)."""
    out = np.zeros((opd_nm.shape[0], sensor.n_slopes))
    for i, intensity in enumerate(sensor.pyramid.intensity(np.asarray(opd_nm, dtype=np.float32))):
        for _ in range(frames):
            out[i] += sensor.slopes_of_frame(sensor.detector.read(intensity, sensor.photons_per_frame, rng))
    return out / frames


@blas.on_one_thread
def measured_calibration(
    calibration: Calibration, conditions: CalibrationNoise, detector: Detector = Detector(), L0_m: float = defaults.L0_M
) -> Calibration:
    """``calibration`` with D measured in ``conditions`` (finite flux and/or around a residual
    of outer scale ``L0_m``; see the module) and R = D^+ of it.  Around residuals, each of the
    ``SCREENS`` realisations is measured with ``frames`` frames per push."""
    pupil = calibration.setup.pyramid.pupil
    shapes = calibration.basis.shapes(pupil)
    maps = mode_maps(shapes, pupil)
    rng = np.random.default_rng(conditions.seed)
    if conditions.photons_per_frame > 0:
        sensor = WavefrontSensor(Pyramid(calibration.setup.pyramid), detector, conditions.photons_per_frame)
        slopes_of = lambda opd: averaged_slopes(sensor, opd, conditions.frames, rng)  # noqa: E731
    else:
        sensor, slopes_of = calibration_sensor(calibration.setup.pyramid), None
    arounds: list[np.ndarray | None] = [None]
    if conditions.seeing_arcsec > 0:
        level = CorrectionLevel(conditions.seeing_arcsec, L0_m)
        arounds = list(residual_screens(level, shapes, pupil, SCREENS, np.random.default_rng([conditions.seed, 1])))
    D = np.mean([push_pull(sensor, maps, calibration.setup.push_nm, around=a, slopes_of=slopes_of) for a in arounds], axis=0)
    return dataclasses.replace(calibration, interaction_matrix=D, reconstructor=np.linalg.pinv(D), from_cache=False)
