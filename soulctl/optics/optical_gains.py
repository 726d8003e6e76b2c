"""Modal optical gains of the pyramid in partial correction.

In closed loop the PWFS sees the residual phase, not a flat wavefront; the residual spreads
the modulated PSF and every mode's sensitivity drops (Esposito et al. 2001; Korkiakoski et al.
2008; Deo et al. 2019).  The optical gain of mode i is the ratio of its sensitivity around a
residual phase to its diffraction-limited sensitivity:

    gamma_i = < D_i(phi), D_i(0) > / |D_i(0)|^2 ,   averaged over residual realisations phi,

where D_i(phi) is the push-pull response of mode i around phi (the interaction-matrix column
measured there) projected on the calibrated column D_i(0).

Correction level (the residual statistics): von Karman turbulence of the given seeing and L0,
minus its projection on the controlled modes, of which a fraction ``controlled_fraction`` of
the amplitude is left (default 0.1: the servo-lag and noise residual of the controlled modes,
~10 % of their turbulent amplitude in a well-tuned loop; a proposal).  Uncontrolled modes
(the fitting error) are left whole.  The paper tabulates chi_i for 0.8" seeing; MGM uses such
a table.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .. import blas, defaults
from ..errors import InputError
from ..files import atomic_write_text, read_input_text
from ..ranges import FRACTION, OPTICAL_GAIN, OUTER_SCALE_M, SEEING_ARCSEC
from .atmosphere import fft_phase_screen, r0_from_seeing
from .calibration import Calibration, calibration_sensor, mode_maps, push_pull
from .pupil import Pupil

CHI_TABLE_SEEING_ARCSEC = 0.8  # the seeing of the paper's chi_i table, the optimisers' plant model
SCREENS = 4  # residual phase realisations averaged per table


@dataclass(frozen=True)
class CorrectionLevel:
    seeing_arcsec: float = CHI_TABLE_SEEING_ARCSEC
    L0_m: float = defaults.L0_M
    controlled_fraction: float = 0.1

    def __post_init__(self):
        SEEING_ARCSEC.check(self.seeing_arcsec, "--seeing")
        OUTER_SCALE_M.check(self.L0_m, "--L0")
        FRACTION.check(self.controlled_fraction, "--controlled-fraction")


def residual_screens(level: CorrectionLevel, shapes: np.ndarray, pupil: Pupil, n_screens: int, rng: np.random.Generator) -> np.ndarray:
    """(n_screens, n, n) residual OPD maps (nm) at ``level`` for modes ``shapes`` (n_valid, n_modes)."""
    r0 = r0_from_seeing(level.seeing_arcsec)
    out = np.zeros((n_screens, pupil.n_pixels, pupil.n_pixels), dtype=np.float32)
    for k in range(n_screens):
        phi = fft_phase_screen(pupil.n_pixels, pupil.pixel_scale_m, r0, level.L0_m, rng)[pupil.mask]
        phi = phi - phi.mean()
        a = shapes.T @ phi / pupil.n_valid
        out[k][pupil.mask] = phi - (1.0 - level.controlled_fraction) * (shapes @ a)
    return out


@dataclass(frozen=True)
class OpticalGainTable:
    gains: np.ndarray  # (n_modes,) mean over the residual realisations
    spread: np.ndarray  # (n_modes,) standard deviation over them
    level: CorrectionLevel
    binning: int
    modulation_lambda_over_d: float
    n_screens: int
    seed: int
    residual_nm: float  # mean RMS of the residual screens on the pupil
    oversampling: int = 2  # the pyramid's: a table applies to a sensor of the same sampling and field
    wfs_field_arcsec: float = 0.0

    def to_csv(self) -> str:
        head = [
            "# Modal optical gains of the PWFS in partial correction (soulctl optics gains)",
            f"# seeing_arcsec = {self.level.seeing_arcsec}, L0_m = {self.level.L0_m}, "
            f"controlled_fraction = {self.level.controlled_fraction}",
            f"# binning = {self.binning}, modulation_lambda_over_d = {self.modulation_lambda_over_d}, "
            f"modes = {len(self.gains)}, screens = {self.n_screens}, seed = {self.seed}, residual_nm = {self.residual_nm:.1f}",
            f"# oversampling = {self.oversampling}, wfs_field_arcsec = {self.wfs_field_arcsec}",
            "mode,optical_gain,spread",
        ]
        rows = [f"{i + 1},{g:.5f},{s:.5f}" for i, (g, s) in enumerate(zip(self.gains, self.spread))]
        return "\n".join(head + rows) + "\n"

    def write_csv(self, path: str | Path) -> None:
        atomic_write_text(path, self.to_csv())

    def to_dict(self) -> dict:
        return {
            "level": asdict(self.level),
            "binning": self.binning,
            "modulation_lambda_over_d": self.modulation_lambda_over_d,
            "oversampling": self.oversampling,
            "wfs_field_arcsec": self.wfs_field_arcsec,
            "n_screens": self.n_screens,
            "seed": self.seed,
            "residual_nm": self.residual_nm,
            "optical_gains": [round(float(g), 5) for g in self.gains],
            "spread": [round(float(s), 5) for s in self.spread],
        }


def read_optical_gains(path: str | Path) -> np.ndarray:
    """The optical-gain column of a table written by :meth:`OpticalGainTable.write_csv`."""
    try:
        with open(path) as f:
            lines = [ln.strip() for ln in f if ln.strip() and not ln.startswith("#")]
    except OSError as e:
        raise InputError(f"cannot read optical-gain table {path}: {e.strerror or e}") from None
    try:
        rows = [ln.split(",") for ln in lines if not ln.startswith("mode")]
        modes = np.array([int(r[0]) for r in rows])
        gains = np.array([float(r[1]) for r in rows])
    except (ValueError, IndexError) as e:
        raise InputError(f"optical-gain table {path} is malformed: {e}") from None
    if not np.array_equal(modes, np.arange(1, len(modes) + 1)) or not np.all((gains > 0) & (gains <= 2)):
        raise InputError(f"optical-gain table {path} must list modes 1..N in order with gains in (0, 2]")
    return gains


@blas.on_one_thread
def optical_gains(calibration: Calibration, level: CorrectionLevel, n_screens: int = SCREENS, seed: int = 1) -> OpticalGainTable:
    """The modal optical gains of ``calibration``'s sensor and modes at ``level`` (see the
    module docstring): ``2 n_modes n_screens`` noiseless PWFS frames."""
    if not (1 <= n_screens <= 1000):
        raise InputError(f"screens must be in 1..1000, got {n_screens}")
    config = calibration.setup.pyramid
    sensor = calibration_sensor(config)
    pupil = sensor.pupil
    shapes = calibration.basis.shapes(pupil)
    maps = mode_maps(shapes, pupil)
    D0 = calibration.interaction_matrix
    norm = np.sum(D0**2, axis=0)
    rng = np.random.default_rng(seed)
    residuals = residual_screens(level, shapes, pupil, n_screens, rng)
    gains = np.empty((n_screens, D0.shape[1]))
    for k, phi in enumerate(residuals):
        D = push_pull(sensor, maps, calibration.setup.push_nm, around=phi)
        gains[k] = np.sum(D * D0, axis=0) / norm
    rms = float(np.mean([np.sqrt(np.mean(r[pupil.mask] ** 2)) for r in residuals]))
    return OpticalGainTable(
        gains=gains.mean(axis=0),
        spread=gains.std(axis=0),
        level=level,
        binning=config.binning,
        modulation_lambda_over_d=config.modulation_lambda_over_d,
        n_screens=n_screens,
        seed=seed,
        residual_nm=rms,
        oversampling=config.oversampling,
        wfs_field_arcsec=config.field_of_view_arcsec,
    )


def read_optical_gain_table(path: str | Path, n_modes: int) -> np.ndarray:
    """gamma_i of a table as ``OpticalGainTable.to_csv`` writes it (`optics gains --out`): lines
    mode,optical_gain[,spread] after a header naming those columns, comments '#'; each of the
    modes 1..n_modes once, each gain in OPTICAL_GAIN (InputError naming the file and line)."""
    lines = [
        (i + 1, ln)
        for i, ln in enumerate(read_input_text(path, "optical gain table").splitlines())
        if ln.strip() and not ln.lstrip().startswith("#")
    ]
    if not lines or [c.strip() for c in lines[0][1].split(",")][:2] != ["mode", "optical_gain"]:
        raise InputError(
            f"optical gain table {path}: the first line must be the header mode,optical_gain[,spread] (as 'optics gains --out' writes)"
        )
    gains = np.full(n_modes, np.nan)
    for n, line in lines[1:]:
        cells = [c.strip() for c in line.split(",")]
        try:
            mode, value = int(cells[0]), float(cells[1])
        except (ValueError, IndexError):
            raise InputError(f"optical gain table {path}, line {n}: expected mode,optical_gain, got {line.strip()[:60]!r}") from None
        if not 1 <= mode <= n_modes or not np.isnan(gains[mode - 1]):
            raise InputError(f"optical gain table {path}, line {n}: mode {mode} must be one of 1..{n_modes}, each once")
        gains[mode - 1] = OPTICAL_GAIN.check(value, f"optical gain table {path}, line {n}: optical_gain")
    if np.isnan(gains).any():
        raise InputError(
            f"optical gain table {path} lacks mode {int(np.flatnonzero(np.isnan(gains))[0]) + 1} (the record has {n_modes} modes)"
        )
    return gains
