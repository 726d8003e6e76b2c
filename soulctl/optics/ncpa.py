"""Non-common-path aberrations (NCPA): a static OPD that the science camera sees and the
pyramid does not.

* The aberration: a random map with a power-law PSD, |f|^-exponent (2 by default: the
  polishing errors of optics, a proposal), piston-free, scaled to ``rms_nm`` on the pupil; the
  instrument's own draw (``seed``), the same whatever the run's seed.  The paper's daytime
  images carried ~100 nm of NCPA that the loop did not compensate (LUCI1).
* Compensation, as LBT does it (Esposito et al. 2020): reference-slope offsets, the slopes the
  calibrated pyramid would give for minus the aberration's projection a on the controlled
  modes, s_off = D (-a), subtracted from the RTC's slopes after the sensitivity k scales them:
  s = k s_wfs - s_off.  In closed loop the pyramid answers with its optical gain gamma_i, so
  the loop settles where k gamma_i D a_wfs = -D a: the mirror applies -a_i / (k gamma_i), and
  the science path keeps a_i (1 - 1 / (k gamma_i)).  With k = 1 and gamma < 1 the offsets are
  over-applied (gamma = 0.6 leaves -0.67 a: no better than none); OGTL, holding k gamma = 1 on
  its probed mode, makes them right there and near it.  What lies outside the controlled modes
  stays whole.
* Partial offsets (``offset_fraction`` f, ``defaults.NCPA_OFFSET_FRACTION``): the RTC applies
  f s_off, and the science path keeps (1 - f) a on the controlled modes ((1 - f)^2 of their
  variance).  The pyramid is not linear: in full, the offsets hold its operating point at -a,
  and a turbulent excursion can tip the loop into a false lock, a large static low-order
  shape (~300 nm at R10.9, 1.0") to which the pyramid's response has folded to ~0 and which
  the RTC cannot see (docs/physics.md).  Half the offsets kept every seed tried out of it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..defaults import NCPA_OFFSET_FRACTION as OFFSET_FRACTION
from ..ranges import NCPA_EXPONENT, NCPA_OFFSET_FRACTION, NCPA_RMS_NM, SEED
from .pupil import Pupil


@dataclass(frozen=True, kw_only=True)
class NcpaSpec:
    rms_nm: float = 0.0  # on the pupil, piston removed
    exponent: float = 2.0  # PSD ~ |f|^-exponent
    compensated: bool | None = False  # reference-slope offsets for the controlled modes' part; None: with OGTL (run_config)
    seed: int = 1  # the instrument's draw
    offset_fraction: float = OFFSET_FRACTION  # of the offsets the RTC applies

    def __post_init__(self):
        NCPA_RMS_NM.check(self.rms_nm, "ncpa.rms_nm")
        NCPA_EXPONENT.check(self.exponent, "ncpa.exponent")
        NCPA_OFFSET_FRACTION.check(self.offset_fraction, "ncpa.offset_fraction")
        SEED.check(self.seed, "ncpa.seed")

    @property
    def active(self) -> bool:
        return self.rms_nm > 0


def ncpa_opd(spec: NcpaSpec, pupil: Pupil) -> np.ndarray:
    """(n_valid,) the aberration's OPD (nm) on the pupil pixels: white noise filtered by
    |f|^(-exponent/2) on a grid twice the pupil (no wrap-around correlation), piston removed,
    scaled to ``rms_nm``."""
    n = 2 * pupil.n_pixels
    rng = np.random.default_rng(spec.seed)
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(n), np.fft.fftfreq(n), indexing="ij"))
    f[0, 0] = np.inf  # no piston
    noise = rng.standard_normal((n, n)) + 1j * rng.standard_normal((n, n))
    field = np.fft.ifft2(noise * f ** (-spec.exponent / 2)).real[: pupil.n_pixels, : pupil.n_pixels]
    opd = field[pupil.mask] - field[pupil.mask].mean()
    rms = float(np.sqrt(np.mean(opd**2)))
    return opd * (spec.rms_nm / rms) if rms > 0 else opd


@dataclass(frozen=True)
class NonCommonPath:
    """What the loop holds of the NCPA: the science path's OPD (n_valid,) and the RTC's
    reference-slope offsets (n_slopes,; None: not compensated)."""

    opd: np.ndarray
    slope_offset: np.ndarray | None


def non_common_path(spec: NcpaSpec, pupil: Pupil, shapes: np.ndarray, interaction_matrix: np.ndarray) -> NonCommonPath:
    """The aberration of ``spec`` on ``pupil`` and, when compensated, the offsets the RTC
    applies: ``spec.offset_fraction`` of those for the calibration's controlled modes
    ``shapes`` and interaction matrix."""
    opd = ncpa_opd(spec, pupil)
    offset = (spec.offset_fraction * slope_offsets(opd, shapes, interaction_matrix)).astype(np.float32) if spec.compensated else None
    return NonCommonPath(opd, offset)


def controlled_part(opd: np.ndarray, shapes: np.ndarray) -> np.ndarray:
    """a = S^T opd / n_valid: the coefficients (nm) of ``opd`` (n_valid,) on the controlled
    modes ``shapes`` (n_valid, n_modes, orthonormal on the pupil)."""
    return shapes.T @ opd / shapes.shape[0]


def slope_offsets(opd: np.ndarray, shapes: np.ndarray, interaction_matrix: np.ndarray) -> np.ndarray:
    """s_off = D (-a): the reference-slope offsets that compensate ``opd`` on the controlled
    modes ``shapes`` (a: ``controlled_part``)."""
    return interaction_matrix @ (-controlled_part(opd, shapes))
