"""Calibration: the modal basis on the mirror, the interaction matrix and the reconstructor.

* Interaction matrix D (n_slopes x n_modes), slopes per nm RMS of each mode, by push-pull of
  the controlled modes with ``push_nm`` around the unaberrated (diffraction-limited) reference:
  D_i = (s(+a m_i) - s(-a m_i)) / 2a, noiseless frames through the same slope computer.
* Reconstructor R = D^+ (Moore-Penrose pseudo-inverse, all modes kept): modes = R s.
* Reference slopes: those of the unaberrated beam (subtracted by the slope computer).

Both the basis and the calibration are cached on disk under a key of everything that
determines them (:mod:`soulctl.optics.cache`); ``cache=ArrayCache(None)`` forces a fresh
computation.  Each states the arrays and shapes it expects of an entry (``basis_entry``,
``calibration_entry``); an entry that is not that, or fails its checksum, is recomputed.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from .. import blas, defaults
from ..errors import InputError
from ..ranges import MODES
from .asm import SIGN_SEED, AsmGeometry, ModalBasis, kl_basis
from .cache import ArrayCache, EntrySpec, cache_key
from .detector import Detector
from .pupil import Pupil
from .pwfs import SUBAPERTURES_BIN1, Pyramid, PyramidConfig
from .registration import Misregistration
from .sensor import WavefrontSensor

UNKEYED_INFLUENCE = "gaussian"  # the model whose cache key predates the choice (BasisSetup.key)
BASIS_PIXELS = 80  # pupil sampling on which the KL modes are computed (~3.5 pixels per actuator)
MAX_SLOPES = 2 * SUBAPERTURES_BIN1**2  # sx and sy of every sub-aperture at binning 1


@dataclass(frozen=True)
class BasisSetup:
    asm: AsmGeometry = field(default_factory=AsmGeometry)
    L0_m: float = defaults.L0_M
    pixels: int = BASIS_PIXELS

    def key(self) -> str:
        """The cache key; the Gaussian mirror keeps the key it had before the influence model
        was a choice, so cached bases stay valid (whatever the default model)."""
        asm = {k: v for k, v in asdict(self.asm).items() if k != "influence" or v != UNKEYED_INFLUENCE}
        return cache_key("basis", {"asm": asm, "L0_m": self.L0_m, "pixels": self.pixels, "sign_seed": SIGN_SEED})


def basis_entry(setup: BasisSetup) -> EntrySpec:
    """A cached basis: M (actuators x modes), M_inv (modes x actuators) and the modes'
    variance, with 2 .. actuators - 1 modes (Tip/Tilt + KL, piston removed)."""
    n = setup.asm.n_actuators
    return EntrySpec({"M": (n, "modes"), "M_inv": ("modes", n), "variance": ("modes",)}, {"modes": (2, n - 1)})


def modal_basis(setup: BasisSetup, cache: ArrayCache = ArrayCache(None), refresh: bool = False) -> ModalBasis:
    """The ASM's Tip/Tilt + KL basis (all its modes), from the cache when there (not with
    ``refresh``: recomputed and stored)."""
    key = setup.key()
    hit = None if refresh else cache.load(key, basis_entry(setup))
    if hit is not None:
        return ModalBasis(hit["M"], hit["M_inv"], hit["variance"], setup.asm, setup.L0_m)
    pupil = Pupil(setup.pixels, setup.asm.diameter_m, setup.asm.obstruction)
    basis = kl_basis(setup.asm, pupil, setup.L0_m)
    cache.store(key, {"M": basis.M, "M_inv": basis.M_inv, "variance": basis.variance})
    return basis


# At oversampling 1 the pupil has 40 pixels across for ~30 actuators: the high-order modes of
# the 20x20 and 40x40 configurations are barely sampled and their loop hardly converges
# (R13, 20x20, 250 modes: 812 nm residual against 233 nm at oversampling 2).
MAX_MODES_AT_OVERSAMPLING_1 = 90


def check_sampling(n_modes: int, oversampling: int) -> None:
    """InputError when the pupil's sampling is too coarse for ``n_modes`` (oversampling 1)."""
    if oversampling == 1 and n_modes > MAX_MODES_AT_OVERSAMPLING_1:
        raise InputError(
            f"--oversampling 1 samples the pupil on 40 pixels (1.4 per actuator pitch), too coarse for "
            f"{n_modes} modes: accepted up to {MAX_MODES_AT_OVERSAMPLING_1} modes; use 2..4"
        )


@dataclass(frozen=True)
class CalibrationSetup:
    pyramid: PyramidConfig
    n_modes: int
    basis: BasisSetup = field(default_factory=BasisSetup)
    push_nm: float = 10.0

    def __post_init__(self):
        if not (0 < self.push_nm <= 100):
            raise InputError(f"calibration push must be in (0, 100] nm RMS, got {self.push_nm}")
        MODES.check(self.n_modes, "modes")
        check_sampling(self.n_modes, self.pyramid.oversampling)

    def key(self) -> str:
        """The cache key; a monochromatic pyramid without a field stop or field of view has the
        key it had before bands and stops existed, so cached calibrations stay valid."""
        optional = ("band_nm", "field_stop_lambda_over_d", "field_of_view_arcsec")
        pyramid = {k: v for k, v in asdict(self.pyramid).items() if k not in optional or v}
        return cache_key("calibration", {"pyramid": pyramid, "n_modes": self.n_modes, "basis": self.basis.key(), "push_nm": self.push_nm})


@dataclass(frozen=True)
class Calibration:
    setup: CalibrationSetup
    basis: ModalBasis  # truncated to the controlled modes
    interaction_matrix: np.ndarray  # (n_slopes, n_modes), slopes per nm
    reconstructor: np.ndarray  # (n_modes, n_slopes), nm per slope
    reference_slopes: np.ndarray
    from_cache: bool
    seconds: float

    @property
    def singular_values(self) -> np.ndarray:
        return np.linalg.svd(self.interaction_matrix, compute_uv=False)

    @property
    def condition_number(self) -> float:
        s = self.singular_values
        return float(s[0] / s[-1])


def mode_maps(shapes: np.ndarray, pupil: Pupil) -> np.ndarray:
    """(n_modes, n, n) OPD maps of mode shapes given on the pupil pixels (n_valid, n_modes)."""
    maps = np.zeros((shapes.shape[1], pupil.n_pixels, pupil.n_pixels), dtype=np.float32)
    maps[:, pupil.mask] = shapes.T
    return maps


def push_pull(sensor: WavefrontSensor, maps: np.ndarray, push_nm: float, around: np.ndarray | None = None, slopes_of=None) -> np.ndarray:
    """(n_slopes, n_maps): slope response per nm to each map, by push-pull around ``around``
    (an OPD map; the unaberrated beam when None); ``slopes_of`` maps a stack of OPD maps to
    their slopes (default: the sensor's noiseless ones)."""
    base = np.zeros(maps.shape[1:], dtype=np.float32) if around is None else np.asarray(around, dtype=np.float32)
    slopes_of = slopes_of or sensor.noiseless_slopes
    out = np.empty((sensor.n_slopes, maps.shape[0]))
    chunk = 8
    for start in range(0, maps.shape[0], chunk):
        m = maps[start : start + chunk] * np.float32(push_nm)
        s = slopes_of(np.concatenate([base + m, base - m]))
        k = m.shape[0]
        out[:, start : start + k] = ((s[:k] - s[k:]) / (2 * push_nm)).T
    return out


def calibration_sensor(config: PyramidConfig) -> WavefrontSensor:
    """A noiseless sensor for calibration (normalised slopes do not depend on the flux)."""
    return WavefrontSensor(Pyramid(config), Detector(read_noise_e=0.0, excess_noise=False), photons_per_frame=1.0)


def calibration_entry(setup: CalibrationSetup) -> EntrySpec:
    """A cached calibration: D (slopes x modes), R (modes x slopes) and the reference slopes,
    for the set-up's modes."""
    n = setup.n_modes
    return EntrySpec({"D": ("slopes", n), "R": (n, "slopes"), "reference": ("slopes",)}, {"slopes": (2, MAX_SLOPES)})


def controlled_basis(setup: CalibrationSetup, cache: ArrayCache = ArrayCache(None)) -> ModalBasis:
    """The set-up's controlled modes of the mirror's basis (what a calibration's ``basis`` holds,
    without sensing them)."""
    full = modal_basis(setup.basis, cache)
    if setup.n_modes > full.n_modes:  # the mirror's own count, not a cached entry's, decides
        full = modal_basis(setup.basis, cache, refresh=True)
    if setup.n_modes > full.n_modes:
        raise InputError(f"modes must be in 1..{full.n_modes} for this mirror, got {setup.n_modes}")
    return full.truncated(setup.n_modes)


@blas.on_one_thread  # the same D and R on every machine
def calibrate(setup: CalibrationSetup, cache: ArrayCache = ArrayCache(None)) -> Calibration:
    """The interaction matrix, reconstructor and reference slopes of ``setup``, from the cache
    when there (see the module docstring)."""
    t0 = time.perf_counter()
    basis = controlled_basis(setup, cache)
    key = setup.key()
    hit = cache.load(key, calibration_entry(setup))
    if hit is not None:
        return Calibration(setup, basis, hit["D"], hit["R"], hit["reference"], True, time.perf_counter() - t0)
    sensor = calibration_sensor(setup.pyramid)
    if setup.n_modes > sensor.n_slopes:
        raise InputError(
            f"{setup.n_modes} modes cannot be calibrated from the {sensor.n_slopes} slopes of binning {setup.pyramid.binning} "
            f"(an under-determined interaction matrix): accepted at most {sensor.n_slopes} modes"
        )
    maps = mode_maps(basis.shapes(sensor.pupil), sensor.pupil)
    D = push_pull(sensor, maps, setup.push_nm)
    R = np.linalg.pinv(D)
    ref = sensor.reference_slopes.astype(np.float64)
    cache.store(key, {"D": D, "R": R, "reference": ref})
    return Calibration(setup, basis, D, R, ref, False, time.perf_counter() - t0)


@blas.on_one_thread
def moved_mirror_response(calibration: Calibration, registration: Misregistration, cache: ArrayCache = ArrayCache(None)) -> np.ndarray:
    """(n_slopes, n_modes): D', the slopes per nm of the calibration's modes made by the mirror
    as ``registration`` moves it on the pyramid (push-pull as ``calibrate``; noiseless, the
    unaberrated beam), cached with the calibration's set-up.  R D' is the loop's modal
    coupling, the identity when registered."""
    key = cache_key("moved-mirror", {"calibration": calibration.setup.key(), "registration": asdict(registration)})
    spec = EntrySpec({"D": ("slopes", calibration.basis.n_modes)}, {"slopes": (2, MAX_SLOPES)})
    hit = cache.load(key, spec)
    if hit is not None:
        return hit["D"]
    sensor = calibration_sensor(calibration.setup.pyramid)
    basis = calibration.basis
    shapes = np.asarray(basis.geometry.sparse_influence_functions(sensor.pupil, registration=registration) @ basis.M)
    D = push_pull(sensor, mode_maps(shapes, sensor.pupil), calibration.setup.push_nm)
    cache.store(key, {"D": D})
    return D
