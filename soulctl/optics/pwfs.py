"""Diffractive model of the modulated pyramid wavefront sensor (PWFS).

Geometry (all in simulation pixels, ``o`` = oversampling = simulation pixels per binning-1
detector pixel):

* the pupil is sampled on ``n_pup = 40 o`` pixels (40 sub-apertures across at binning 1);
* the field is zero-padded to ``N = 96 o``: 2.4 focal-plane pixels per lambda/D;
* the four pyramid faces tilt the light so that the four pupil images are centred at
  ``N/2 +- 24 o`` in x and y: each image sits in one quadrant of the N x N output plane with a
  gap of 0.2 D between images, and the detector at binning b has (96/b)^2 pixels of
  ``o b`` simulation pixels: 40/20/13.3/10 pixels across a pupil image for b = 1/2/3/4 (at
  b = 3 the pixel grid is shifted by half a pixel so that 13 sub-apertures are lit across);
* the point-spread function is centred on the pyramid's vertex (half a pixel off the FFT
  grid's centre), so an unaberrated beam lights the four faces equally.

Modulation: a circle of radius ``r`` lambda/D travelled during one frame, sampled at
``4 ceil(2 r)`` points (spacing <= pi/4 lambda/D, a multiple of 4 so the four quadrants are
sampled alike; 24 points at 3 lambda/D, SPECULA's 2 round(4 r) there).  Moving the PSF over the
pyramid is the same as moving the pyramid under the PSF, so each modulation point uses the
mask translated by the opposite offset, evaluated analytically: one forward FFT per
wavefront, then one inverse FFT per modulation point (batched, threaded, complex64), the
points summed in fixed shares (``SUM_SHARES``) so that a frame does not depend on the threads.

Sensing wavelength: 750 nm, the effective wavelength of SOUL's 600-950 nm WFS band (Arcetri
semi-analytic error budget).  A polychromatic beam (``band_nm``: wavelengths of equal photon
weight) sums the monochromatic frames of its wavelengths, each with the modulation at the same
angle (``modulation_lambda_over_d`` is in lambda/D at ``wavelength_m``) and the same pupil
images (the pyramid's deflection is taken as achromatic); the same OPD is less phase at the
band's red end, which keeps the sensor linear over larger residuals.
Field: the focal plane spans +-20 o lambda/D (0.75" at o = 2) and light beyond it wraps around.
A field of view (``field_of_view_arcsec``; SOUL's is 2.1") puts a stop at its edge and reads
the OPD interpolated on a sensing pupil of ``o'`` pixels per detector pixel, the least whose
focal plane holds the stop (``optics.pupil.PupilResampler``, as SPECULA's pyramid reaches its
field of view).
Intensities returned by :meth:`Pyramid.intensity` are binned detector frames normalised so
that an unaberrated frame holds a total of 1; multiply by the photons per frame.
"""

from __future__ import annotations

import math
import numbers
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from ..errors import InputError
from ..ranges import WFS_FIELD_OF_VIEW_ARCSEC
from .pupil import LBT_DIAMETER_M, LBT_OBSTRUCTION, MAS_PER_RAD, Pupil, PupilResampler


def _fft():
    """scipy.fft, imported at the first transform, not at the top: the CLI starts without it."""
    import scipy.fft

    return scipy.fft


SUBAPERTURES_BIN1 = 40
WFS_WAVELENGTH_M = 750e-9
MAX_BAND_WAVELENGTHS = 9
_FFT_PER_PUPIL = 96 / 40  # N / n_pup
_SEPARATION_PER_PUPIL = 48 / 40  # distance between pupil image centres / n_pup


def modulation_points(radius_lambda_over_d: float) -> int:
    """Points sampled on the modulation circle: 4 ceil(2 r), 1 without modulation."""
    return 1 if radius_lambda_over_d == 0 else 4 * math.ceil(2 * radius_lambda_over_d)


@dataclass(frozen=True)
class PyramidConfig:
    binning: int = 1
    modulation_lambda_over_d: float = 3.0
    wavelength_m: float = WFS_WAVELENGTH_M
    oversampling: int = 2
    valid_threshold: float = 0.5
    diameter_m: float = LBT_DIAMETER_M
    obstruction: float = LBT_OBSTRUCTION
    n_modulation: int | None = None  # None: the 4 ceil(2 r) rule
    band_nm: tuple[float, ...] = ()  # a polychromatic beam's wavelengths (equal photons); () monochromatic
    field_stop_lambda_over_d: float = 0.0  # radius of a field stop around the vertex, lambda/D at wavelength_m; 0: none
    # The WFS's field of view (a diameter, arcsec; 0: none).  The pyramid then reads the OPD
    # interpolated on a sensing pupil fine enough for its focal plane to hold the field, with a
    # stop at its edge (``sensing_oversampling``, ``stop_lambda_over_d``); docs/physics.md.
    field_of_view_arcsec: float = 0.0

    def __post_init__(self):
        if self.binning not in (1, 2, 3, 4):
            raise InputError(f"binning must be one of 1, 2, 3, 4, got {self.binning}")
        r = self.modulation_lambda_over_d
        if not (math.isfinite(r) and 0 <= r <= 20):
            raise InputError(f"modulation must be in 0..20 lambda/D, got {r}")
        if not (math.isfinite(self.wavelength_m) and 300e-9 <= self.wavelength_m <= 3e-6):
            raise InputError(f"WFS wavelength must be in 300..3000 nm, got {self.wavelength_m * 1e9:g} nm")
        if self.oversampling not in (1, 2, 3, 4):
            raise InputError(f"oversampling must be 1..4 simulation pixels per detector pixel, got {self.oversampling}")
        if not (0 < self.valid_threshold < 1):
            raise InputError(f"valid sub-aperture threshold must be in (0, 1), got {self.valid_threshold}")
        if self.n_modulation is not None and not (1 <= self.n_modulation <= 1000):
            raise InputError(f"modulation points must be 1..1000, got {self.n_modulation}")
        fov = self.field_of_view_arcsec
        if not WFS_FIELD_OF_VIEW_ARCSEC.contains(fov) or (fov > 0 and self.field_stop_lambda_over_d > 0):
            raise InputError(
                f"WFS field of view must be {WFS_FIELD_OF_VIEW_ARCSEC.text()} (0: none), without a field stop in lambda/D, "
                f"got {fov} (field stop {self.field_stop_lambda_over_d} lambda/D)"
            )
        stop, field = self.stop_lambda_over_d, self.field_lambda_over_d
        if not (math.isfinite(stop) and (stop == 0 or r < stop <= field)):
            raise InputError(
                f"field stop must be 0 (none) or above the modulation ({r:g}) up to the simulated field ({field:g} lambda/D at "
                f"oversampling {self.oversampling}), got {stop}"
            )
        band = self.band_nm
        if len(band) > MAX_BAND_WAVELENGTHS or not all(isinstance(w, numbers.Real) and math.isfinite(w) and 300 <= w <= 3000 for w in band):
            raise InputError(f"WFS band must be 1..{MAX_BAND_WAVELENGTHS} wavelengths in 300..3000 nm, got {list(band)}")
        object.__setattr__(self, "band_nm", tuple(sorted(float(w) for w in band)))  # one form (and cache key) per band
        for w in self.band_nm:
            try:
                self.monochromatic(w)  # the modulation and the stop in range at every wavelength
            except InputError as e:
                raise InputError(f"WFS band: at {w:g} nm, {e}") from None

    def monochromatic(self, wavelength_nm: float) -> PyramidConfig:
        """This configuration at one wavelength of its band: the modulation and the field stop
        at the same angle."""
        scale = self.wavelength_m / (wavelength_nm * 1e-9)
        radius, stop = self.modulation_lambda_over_d * scale, self.field_stop_lambda_over_d * scale
        return replace(self, wavelength_m=wavelength_nm * 1e-9, modulation_lambda_over_d=radius, field_stop_lambda_over_d=stop, band_nm=())

    @property
    def stop_lambda_over_d(self) -> float:
        """The field stop's radius (lambda/D at wavelength_m; 0: none): the field of view's half
        or ``field_stop_lambda_over_d``."""
        if self.field_of_view_arcsec > 0:
            return self.field_of_view_arcsec / 2 * 1e3 / MAS_PER_RAD * self.diameter_m / self.wavelength_m
        return self.field_stop_lambda_over_d

    @property
    def sensing_oversampling(self) -> int:
        """Simulation pixels per binning-1 detector pixel of the pyramid's own propagation:
        ``oversampling``, or with a field of view the least at which the focal plane
        (+-20 o lambda/D) holds its stop (3 for SOUL's 2.1" at 750 nm: +-60 against a radius of 56)."""
        if self.field_of_view_arcsec <= 0:
            return self.oversampling
        return max(self.oversampling, math.ceil(self.stop_lambda_over_d / (SUBAPERTURES_BIN1 / 2)))

    @property
    def field_lambda_over_d(self) -> float:
        """Half-width of the simulated focal plane: N/2 pixels at N / n_pup per lambda/D."""
        return self.sensing_pupil.n_pixels / 2

    @property
    def pupil(self) -> Pupil:
        """The grid of the OPD the pyramid reads (the loop's, the mirror's)."""
        return Pupil(SUBAPERTURES_BIN1 * self.oversampling, self.diameter_m, self.obstruction)

    @property
    def sensing_pupil(self) -> Pupil:
        """The grid of the pyramid's propagation: ``pupil``, or finer with a field of view."""
        return Pupil(SUBAPERTURES_BIN1 * self.sensing_oversampling, self.diameter_m, self.obstruction)

    @property
    def fft_size(self) -> int:
        return round(_FFT_PER_PUPIL * self.sensing_pupil.n_pixels)

    @property
    def detector_pixel(self) -> int:
        """Simulation pixels per detector pixel side (of the sensing pupil)."""
        return self.sensing_oversampling * self.binning

    @property
    def frame_shape(self) -> tuple[int, int]:
        n = self.fft_size // self.detector_pixel
        return n, n

    @property
    def points(self) -> int:
        return self.n_modulation or modulation_points(self.modulation_lambda_over_d)


def _available_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


# The modulation points are summed in this many fixed shares (point k in share k mod SHARES),
# each share's points in a fixed order and the shares' totals added in index order, whatever
# the number of threads: float32 sums depend on their order, and a closed loop amplifies a
# last-bit difference, so a frame must not depend on the machine's cores (same seed, same run).
SUM_SHARES = 4  # at most 4 threads share the points; on two cores 2 and 4 shares run alike, 8 ~8 % slower (smaller FFT calls)
_CHUNK_BYTES = 4 << 20


def _chunk(n: int, points: int) -> int:
    """Points per FFT call: a few MB of complex64 fields."""
    return max(1, min(points, _CHUNK_BYTES // (8 * n * n)))


class _Scratch:
    """One propagation thread's buffers: a chunk of fields it transforms in place and |field|^2
    summed over the chunk."""

    def __init__(self, n: int, chunk: int):
        self.field = np.empty((chunk, n, n), dtype=np.complex64)
        self.square = np.empty((n, 2 * n), dtype=np.float32)


class Pyramid:
    """The PWFS optics: wavefront OPD (nm, on the pupil grid) -> binned detector intensity."""

    def __init__(self, config: PyramidConfig, workers: int = -1):
        """``workers``: threads for the propagation, -1 for one per available core."""
        self.config = config
        self.pupil = config.pupil
        self.workers = _available_cores() if workers == -1 else workers
        if self.workers < 1:
            raise InputError(f"workers must be >= 1 or -1 (one per core), got {workers}")
        self._parts = [Pyramid(config.monochromatic(w), workers) for w in config.band_nm]
        if not self._parts:
            self._monochromatic(config)
        self._pool: ThreadPoolExecutor | None = None
        self._norm = 1.0 / (self._raw_total())

    def _monochromatic(self, config: PyramidConfig) -> None:
        """The propagation's geometry, masks and per-thread scratch at one wavelength."""
        self._sensing = sensing = config.sensing_pupil
        # with a field of view, the OPD is interpolated on the finer sensing pupil first
        self._resample = PupilResampler(self.pupil, sensing) if sensing != self.pupil else None
        n_pup, N = sensing.n_pixels, config.fft_size
        self._offset = (N - n_pup) // 2  # the pupil sits at the centre of the padded field
        # At binning 3 a pupil image is 13.3 detector pixels wide: shifting the pixel grid by
        # half a pixel centres it on 13 full pixels (13 sub-apertures across, as SOUL's table).
        self._grid_shift = round(1.5 * config.sensing_oversampling) if config.binning == 3 else 0
        # Half a focal-plane pixel of tilt puts the PSF on the vertex between four pixels.
        idx = np.arange(n_pup) + self._offset
        half = np.exp(-1j * np.pi * idx / N)
        self._amplitude = (np.outer(half, half) * sensing.mask).astype(np.complex64)
        self._masks = self._modulated_masks()
        # The fixed shares of the modulation points (SUM_SHARES), one total each; per thread
        # its scratch buffers.  Thread t sums shares t, t + threads, ...
        self._shares = [range(k, config.points, SUM_SHARES) for k in range(min(SUM_SHARES, config.points))]
        self._chunk = _chunk(N, len(self._shares[0]))
        self._totals = np.empty((len(self._shares), N, 2 * N), dtype=np.float32)
        threads = min(self.workers, len(self._shares))
        self._scratch = [_Scratch(N, self._chunk) for _ in range(threads)]

    def _modulated_masks(self) -> np.ndarray:
        """(points, N, N) complex64: the pyramid's transmission shifted by each modulation offset."""
        c = self.config
        N = c.fft_size
        f = np.fft.fftfreq(N, 1.0 / N)  # focal-plane pixel index, FFT order
        shift = _SEPARATION_PER_PUPIL * self._sensing.n_pixels / 2  # pupil image offset, pixels
        pixels_per_lambda_over_d = N / self._sensing.n_pixels
        radius = c.modulation_lambda_over_d * pixels_per_lambda_over_d
        angles = 2 * np.pi * np.arange(c.points) / c.points
        masks = np.empty((c.points, N, N), dtype=np.complex64)
        for k, a in enumerate(angles):
            du, dv = radius * np.cos(a), radius * np.sin(a)
            u = f + du + 0.5  # position relative to the vertex (at -0.5 before modulation)
            v = f + dv + 0.5
            # The pyramid's phase is -2 pi shift (|u| + |v|) / N: the face of sign (su, sv) is a
            # tilt that moves its pupil image by (su, sv) * shift.
            phase_u = -2 * np.pi * np.abs(u) * shift / N
            phase_v = -2 * np.pi * np.abs(v) * shift / N
            masks[k] = np.exp(1j * (phase_v[:, None] + phase_u[None, :]))
            if c.stop_lambda_over_d > 0:  # the stop sits on the pyramid: it moves with it
                masks[k] *= (u[None, :] ** 2 + v[:, None] ** 2) <= (c.stop_lambda_over_d * pixels_per_lambda_over_d) ** 2
        return masks

    def _raw_total(self) -> float:
        return float(self._raw(np.zeros((1,) + (self.pupil.n_pixels,) * 2))[0].sum())

    def _raw(self, opd_nm: np.ndarray) -> np.ndarray:
        """Unnormalised binned intensity for a batch of OPD maps (batch, n_pup, n_pup); a
        band's: the mean of its wavelengths' normalised frames (equal photons)."""
        if self._parts:
            self._share_pool()
            frames = np.stack([p._raw(opd_nm) * np.float32(p._norm) for p in self._parts])
            return frames.mean(axis=0, dtype=np.float32)
        c = self.config
        if self._resample is not None:
            opd_nm = self._resample(opd_nm)
        N, o, n_pup = c.fft_size, self._offset, self._sensing.n_pixels
        k = 2 * np.pi / (c.wavelength_m * 1e9)
        batch = opd_nm.shape[0]
        field = np.zeros((batch, N, N), dtype=np.complex64)
        phase = (np.float32(k) * opd_nm).astype(np.float32)
        field[:, o : o + n_pup, o : o + n_pup] = self._amplitude * (np.cos(phase) + 1j * np.sin(phase)).astype(np.complex64)
        focal = _fft().fft2(field, workers=self.workers, overwrite_x=True)
        # |images|^2 summed over the modulation points, kept with real and imaginary parts side
        # by side (N, 2N): they are added together with the detector's binning, in one pass.
        out = np.empty((batch, N, 2 * N), dtype=np.float32)
        for b in range(batch):
            self._map(lambda t, fb=focal[b]: self._modulated_sums(fb, t))
            out[b] = self._totals[0]
            for total in self._totals[1:]:  # in share order
                out[b] += total
        if self._grid_shift:
            out = np.roll(out, (-self._grid_shift, -2 * self._grid_shift), axis=(1, 2))
        p = c.detector_pixel
        n = N // p
        # Binning: 2p adjacent floats (p pixels' real and imaginary parts) by a matrix-vector
        # product, then p rows; 8x faster than one multi-axis sum.
        columns = out.reshape(-1, 2 * p) @ np.ones(2 * p, dtype=np.float32)
        return columns.reshape(batch, n, p, n).sum(axis=2)

    def _modulated_sums(self, focal: np.ndarray, thread: int) -> None:
        """One thread's shares: into each share's total, the sum over its modulation points k
        of |IFFT(focal * mask_k)|^2, as (N, 2N) float32 with real and imaginary parts side by
        side.  The points go through in chunks of a few MB (one FFT call each: few interpreter
        round trips, cache-sized)."""
        sc = self._scratch[thread]
        for index in range(thread, len(self._shares), len(self._scratch)):
            share, total = self._shares[index], self._totals[index]
            total.fill(0.0)
            for start in range(0, len(share), self._chunk):
                points = share[start : start + self._chunk]
                field = sc.field[: len(points)]
                np.multiply(focal, self._masks[points.start : points.stop : points.step], out=field)
                v = _fft().ifft2(field, workers=1, overwrite_x=True).view(np.float32)
                total += np.einsum("kij,kij->ij", v, v, out=sc.square)

    def _share_pool(self) -> None:
        """A band's wavelengths run one after the other: one thread pool serves them all."""
        size = max(len(p._scratch) for p in self._parts)
        if self._pool is None and size > 1:
            self._pool = ThreadPoolExecutor(size, thread_name_prefix="pwfs")
            for p in self._parts:
                p._pool = self._pool

    def _map(self, task):
        if len(self._scratch) == 1:
            return [task(0)]
        if self._pool is None:
            self._pool = ThreadPoolExecutor(len(self._scratch), thread_name_prefix="pwfs")
        return list(self._pool.map(task, range(len(self._scratch))))

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_pool"] = None  # threads do not travel; a copy starts its own
        return state

    def intensity(self, opd_nm: np.ndarray) -> np.ndarray:
        """Binned detector intensity (float32) of one OPD map (n_pup, n_pup) or a batch of them;
        an unaberrated frame sums to 1."""
        opd = np.asarray(opd_nm, dtype=np.float32)
        single = opd.ndim == 2
        if opd.shape[-2:] != (self.pupil.n_pixels,) * 2:
            raise InputError(f"OPD map must be {self.pupil.n_pixels}x{self.pupil.n_pixels} pixels, got {opd.shape[-2:]}")
        raw = self._raw(opd[None] if single else opd) * np.float32(self._norm)
        return raw[0] if single else raw

    @cached_property
    def reference_intensity(self) -> np.ndarray:
        return self.intensity(np.zeros((self.pupil.n_pixels,) * 2, dtype=np.float32))

    @cached_property
    def subaperture_pixels(self) -> np.ndarray:
        """(n_valid, 4, 2) (row, col) of pupil images 1..4 of each valid sub-aperture, in the
        order of the C++ slope computer: 1 = (+x, +y), 2 = (+x, -y), 3 = (-x, +y), 4 = (-x, -y).
        Valid: the four images' flux in the unaberrated frame is at least ``valid_threshold``
        of the brightest sub-aperture's."""
        n = self.config.frame_shape[0]
        h = n // 2  # each pupil image fills one quadrant of the frame
        I = self.reference_intensity
        quadrant = {1: (h, h), 2: (0, h), 3: (h, 0), 4: (0, 0)}  # (row0, col0) of each image's box
        flux = np.sum([I[r0 : r0 + h, c0 : c0 + h] for r0, c0 in quadrant.values()], axis=0)
        rows, cols = np.nonzero(flux >= self.config.valid_threshold * flux.max())
        pixels = np.empty((rows.size, 4, 2), dtype=np.int64)
        for q, (r0, c0) in quadrant.items():
            pixels[:, q - 1, 0] = rows + r0
            pixels[:, q - 1, 1] = cols + c0
        return pixels

    @property
    def valid_map(self) -> np.ndarray:
        """Boolean map (frame side / 2)^2 of the valid sub-apertures."""
        n = self.config.frame_shape[0] // 2
        m = np.zeros((n, n), dtype=bool)
        p = self.subaperture_pixels
        m[p[:, 3, 0], p[:, 3, 1]] = True
        return m
