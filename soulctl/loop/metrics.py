"""What a closed loop delivers: long-exposure PSF and Strehl ratio by image formation, Tip/Tilt
jitter, residual wavefront error, modal variances, rejection and cumulative jitter spectra."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft
from scipy.signal import lfilter, welch

from ..control.delay import fractional_taps
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


def cumulative_spectrum(x: np.ndarray, rate_hz: float, nperseg: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Frequencies and the cumulative RMS from the highest frequency down: sqrt(∫_f^Nyquist PSD)
    (the paper's cumulative Tip/Tilt jitter figure); Welch with a Hann window."""
    n = len(x)
    nperseg = nperseg or min(n, 2 ** int(np.log2(max(n // 4, 16))))
    f, p = welch(x, fs=rate_hz, window="hann", nperseg=nperseg, detrend="constant")
    df = f[1] - f[0]
    cum = np.sqrt(np.cumsum(p[::-1])[::-1] * df)
    return f, cum


def pseudo_open_loop(measured: np.ndarray, command_modes: np.ndarray, delay_frames: float, structure_ba=None) -> np.ndarray:
    """Pseudo-open-loop modes from telemetry: m_pol(k) = m(k) + (mirror modes during frame k),
    the mirror holding the commands delayed by d = n + e frames,
    (1 - e) c(k - n) + e c(k - n - 1) (the delay line's own rule).  Rows are frames; the first
    n + 1 rows use commands from before the record (taken as zero).

    ``structure_ba``: the structural resonance G(z) = b/a on Tip/Tilt (``control.structure``),
    whose wavefront Tip/Tilt adds G u to the mirror's u: the plant is z^-d (1 + G), and so is
    the term added to Tip/Tilt (started at rest with the record; it rings down in ~3/(zeta w0),
    25 ms at 127 Hz)."""
    n, e = fractional_taps(delay_frames)
    c = np.asarray(command_modes, dtype=float)
    shifted = np.zeros_like(c)
    shifted[n:] += (1 - e) * c[: len(c) - n]
    if e:
        shifted[n + 1 :] += e * c[: len(c) - n - 1]
    if structure_ba is not None:
        b, a = structure_ba
        shifted[:, :2] += lfilter(b, a, shifted[:, :2], axis=0)
    return np.asarray(measured, dtype=float) + shifted


def rejection_at(residual: np.ndarray, pseudo_open_loop: np.ndarray, rate_hz: float, f_hz: float, nperseg: int | None = None) -> float:
    """|residual / pseudo-open-loop| at ``f_hz`` from their Welch PSDs (the rejection measured
    from telemetry): sqrt of the PSD ratio, averaged over the bins within 1 Hz."""
    n = len(residual)
    nperseg = nperseg or min(n, 2 ** int(np.log2(max(n // 4, 16))))
    f, pr = welch(residual, fs=rate_hz, nperseg=nperseg)
    _, pp = welch(pseudo_open_loop, fs=rate_hz, nperseg=nperseg)
    band = np.abs(f - f_hz) <= max(1.0, f[1])
    return float(np.sqrt(pr[band].sum() / pp[band].sum()))


@dataclass(frozen=True)
class LoopMetrics:
    """What `loop run` reports.  A figure the run is too short to give is None (not available),
    never NaN or a fake zero: the Strehl ratio and residual need one frame after the skipped
    ones, the jitters two, the jitter above 3 Hz a spectrum resolving 3 Hz, the 13 Hz rejection
    one resolving 5 Hz."""

    band: str
    strehl: float | None
    tt_jitter_mas: float | None  # residual, per axis (RMS of the two axes' RMS)
    tt_jitter_pol_mas: float | None  # pseudo-open loop, per axis
    tt_jitter_pol_3hz_mas: float | None  # pseudo-open loop above 3 Hz (the paper quotes 3-425 Hz)
    residual_nm: float | None  # RMS wavefront error, all modes and fitting
    rejection_13hz: float | None
    frames: int
    skipped_frames: int

    def to_dict(self) -> dict:
        return dict(self.__dict__)
