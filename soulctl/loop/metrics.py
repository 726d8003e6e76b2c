"""What a closed loop delivers: long-exposure PSF and Strehl ratio by image formation, and the
figures `loop run` reports (the Tip/Tilt ones defined once, in ``telemetry.figures``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..optics.pupil import Pupil

# Science bands: central wavelength (m).  FeII is LUCI's 1.646 um narrow band.
BANDS = {"R": 0.64e-6, "I": 0.79e-6, "J": 1.25e-6, "H": 1.65e-6, "FeII": 1.646e-6, "Ks": 2.15e-6}


def band_wavelength(band: str) -> float:
    try:
        return BANDS[band]
    except KeyError:
        raise InputError(f"unknown band '{band}': accepted {', '.join(BANDS)}") from None


class PsfAccumulator:
    """Long-exposure PSF at ``wavelength_m``: the sum of |FFT(pupil exp(i 2 pi OPD / lambda))|^2
    over frames, sampled at ``pad`` pixels per lambda/D (pad = 2: Nyquist).  The Strehl ratio
    is the peak of the long-exposure PSF over the peak of the diffraction-limited one (both
    normalised to unit energy): image formation, not Marechal."""

    def __init__(self, pupil: Pupil, wavelength_m: float, pad: int = 2, static_opd: np.ndarray | None = None):
        self.pupil, self.static_opd = pupil, static_opd  # static_opd: the science path's own (NCPA), nm
        self.wavelength_m = wavelength_m
        self.n = pupil.n_pixels * pad
        self.sum = np.zeros((self.n, self.n))
        self.frames = 0
        self._field = np.zeros((self.n, self.n), dtype=np.complex64)
        self.diffraction_peak = self._image(np.zeros(pupil.n_valid)).max()

    def _image(self, residual_nm: np.ndarray) -> np.ndarray:
        import scipy.fft  # here, not at the top: the CLI starts without it

        f = self._field
        f[:] = 0
        phase = (2 * np.pi / (self.wavelength_m * 1e9) * residual_nm).astype(np.float32)
        f[: self.pupil.n_pixels, : self.pupil.n_pixels][self.pupil.mask] = np.cos(phase) + 1j * np.sin(phase)
        image = np.abs(scipy.fft.fft2(f, workers=-1)) ** 2
        return scipy.fft.fftshift(image) / self.pupil.n_valid**2  # diffraction-limited peak: 1

    def add(self, residual_nm: np.ndarray) -> None:
        """Add one frame's residual OPD (nm on the pupil pixels), seen through the science
        path's static aberration when there is one."""
        self.sum += self._image(residual_nm if self.static_opd is None else residual_nm + self.static_opd)
        self.frames += 1

    @property
    def psf(self) -> np.ndarray:
        """The long-exposure PSF normalised to the diffraction-limited peak (peak = Strehl)."""
        return self.sum / max(self.frames, 1) / self.diffraction_peak

    @property
    def strehl(self) -> float:
        return float(self.psf.max()) if self.frames else float("nan")


@dataclass(frozen=True)
class LoopMetrics:
    """What `loop run` reports, over the window after ``skipped_frames``.  A figure the run
    cannot give is None (not available), never NaN or a fake zero, and ``not_available`` says
    why: a loop that has not settled (the run shorter than twice the settling allowance) has
    none; the jitters need a few frames, the jitter above 3 Hz a spectrum resolving 3 Hz, the
    13 Hz rejection one resolving 5 Hz and a line to reject (``telemetry.figures``)."""

    band: str
    strehl: float | None
    tt_jitter_mas: float | None  # residual (the true wavefront's), per axis
    tt_jitter_pol_mas: float | None  # pseudo-open loop, per axis
    tt_jitter_pol_3hz_mas: float | None  # pseudo-open loop above 3 Hz (the paper quotes 3-425 Hz)
    residual_nm: float | None  # RMS wavefront error, all modes and fitting
    rejection_13hz: float | None
    frames: int
    skipped_frames: int
    jitter_resolution_hz: float | None = None  # the jitter spectra's bins
    not_available: dict[str, str] = field(default_factory=dict)  # figure -> why it is None

    def to_dict(self) -> dict:
        return dict(self.__dict__)
