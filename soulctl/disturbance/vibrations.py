"""Telescope vibrations on Tip/Tilt as damped oscillator lines (tables/lbt_vibrations.toml).

Each line is a second-order oscillator w0^2 / (s^2 + 2 zeta w0 s + w0^2) driven by white
noise, scaled to its RMS: one-sided PSD

    Phi(f) = sigma^2 (8 zeta / w0) |w0^2 / (w0^2 - w^2 + 2j zeta w0 w)|^2,   w = 2 pi f,

whose integral over 0 < f < infinity is sigma^2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import tables
from ..errors import InputError
from ..files import read_toml
from ..ranges import VIBRATION_DAMPING, VIBRATION_FREQUENCY_HZ, VIBRATION_RMS_MAS

AXES = ("tip", "tilt", "mean")
# Named profiles (--vibrations NAME): the proposal the defaults use and the paper's on-sky level.
PROFILES = {"lbt": "lbt_vibrations.toml", "lbt-onsky": "lbt_vibrations_onsky.toml"}
LINE_KEYS = ("frequency_hz", "damping", "tip_mas", "tilt_mas")


@dataclass(frozen=True)
class VibrationLine:
    frequency_hz: float
    damping: float
    tip_mas: float
    tilt_mas: float
    note: str = ""

    def __post_init__(self):
        VIBRATION_FREQUENCY_HZ.check(self.frequency_hz, "vibration frequency_hz")
        VIBRATION_DAMPING.check(self.damping, "vibration damping")
        for name in ("tip_mas", "tilt_mas"):
            VIBRATION_RMS_MAS.check(getattr(self, name), f"vibration {name}")

    def rms_mas(self, axis: str) -> float:
        if axis == "mean":
            return math.sqrt(0.5 * (self.tip_mas**2 + self.tilt_mas**2))
        return self.tip_mas if axis == "tip" else self.tilt_mas

    def ar2_coefficients(self, rate_hz: float) -> tuple[float, float]:
        """(a1, a2) of x_k = a1 x_{k-1} + a2 x_{k-2} + e_k with the sampled oscillator's poles."""
        if not (rate_hz > 2 * self.frequency_hz):
            raise InputError(f"a {self.frequency_hz:g} Hz vibration needs a frame rate above {2 * self.frequency_hz:g} Hz, got {rate_hz:g}")
        w0, z = 2 * np.pi * self.frequency_hz, self.damping
        r = math.exp(-z * w0 / rate_hz)
        return 2 * r * math.cos(w0 * math.sqrt(1 - z * z) / rate_hz), -r * r

    def psd(self, f_hz, axis: str = "mean") -> np.ndarray:
        """One-sided PSD (mas^2/Hz) on Tip, Tilt, or their mean."""
        w = 2 * np.pi * np.asarray(f_hz, dtype=float)
        w0, z = 2 * np.pi * self.frequency_hz, self.damping
        h2 = w0**4 / ((w0**2 - w**2) ** 2 + (2 * z * w0 * w) ** 2)
        return self.rms_mas(axis) ** 2 * (8 * z / w0) * h2


@dataclass(frozen=True)
class VibrationSpectrum:
    lines: tuple[VibrationLine, ...]
    source: str = ""

    def psd(self, f_hz, axis: str = "mean") -> np.ndarray:
        if axis not in AXES:
            raise InputError(f"axis must be one of {', '.join(AXES)}, got '{axis}'")
        f = np.asarray(f_hz, dtype=float)
        return sum((line.psd(f, axis) for line in self.lines), np.zeros(f.shape))

    def below_nyquist(self, rate_hz: float) -> tuple[VibrationSpectrum | None, tuple[VibrationLine, ...]]:
        """(the lines a loop at ``rate_hz`` samples, or None if none; the lines at or above its
        Nyquist frequency, which a real system aliases or filters and the loop leaves out)."""
        kept = tuple(line for line in self.lines if line.frequency_hz < 0.5 * rate_hz)
        dropped = tuple(line for line in self.lines if line.frequency_hz >= 0.5 * rate_hz)
        return (VibrationSpectrum(kept, self.source) if kept else None), dropped

    def variance_mas2(self, axis: str = "mean") -> float:
        return sum(line.rms_mas(axis) ** 2 for line in self.lines)

    def time_series(self, n_frames: int, rate_hz: float, rng: np.random.Generator) -> np.ndarray:
        """(n_frames, 2) Tip and Tilt in mas sampled at ``rate_hz`` (see ``VibrationSource``)."""
        return VibrationSource(self, rate_hz, rng).next(n_frames)

    @classmethod
    def from_dict(cls, data: dict, where: str) -> VibrationSpectrum:
        unknown = sorted(set(data) - {"source", "line"})
        if unknown:
            raise InputError(f"{where}: unknown key {', '.join(unknown)} (accepted: source, [[line]])")
        lines = data.get("line")
        if not isinstance(lines, list) or not lines:
            raise InputError(f"{where}: needs at least one [[line]] table (frequency_hz, damping, tip_mas, tilt_mas)")
        out = []
        for i, line in enumerate(lines):
            if not isinstance(line, dict):
                raise InputError(f"{where}: line {i + 1} must be a table")
            extra = sorted(set(line) - {*LINE_KEYS, "note"})
            if extra:
                raise InputError(f"{where}: line {i + 1} has the unknown key {', '.join(extra)} (accepted: {', '.join(LINE_KEYS)}, note)")
            try:
                values = {k: line[k] for k in LINE_KEYS}
            except KeyError as e:
                raise InputError(
                    f"{where}: line {i + 1} is missing {e.args[0]!r} (each line needs frequency_hz, damping, tip_mas, tilt_mas)"
                ) from None
            for k, v in values.items():
                if not isinstance(v, (int, float)) or isinstance(v, bool):
                    raise InputError(f"{where}: line {i + 1} {k} must be a number, got {v!r}")
            try:
                out.append(VibrationLine(**{k: float(v) for k, v in values.items()}, note=str(line.get("note", ""))))
            except InputError as e:
                raise InputError(f"{where}: line {i + 1}: {e}") from None
        return cls(tuple(out), str(data.get("source", where)))

    @classmethod
    def read(cls, path: str | Path) -> VibrationSpectrum:
        """A vibration file in the format of tables/lbt_vibrations.toml, or a profile name of
        ``PROFILES`` when no regular file of that name exists."""
        if str(path) in PROFILES and not Path(path).is_file():
            path = tables.tables_dir() / PROFILES[str(path)]
        return cls.from_dict(read_toml(path, "vibration file"), str(path))

    @classmethod
    def lbt_default(cls) -> VibrationSpectrum:
        return cls.read(tables.tables_dir() / "lbt_vibrations.toml")


class VibrationSource:
    """Tip/Tilt vibrations (mas) drawn frame block after frame block: each line an AR(2)
    process with the oscillator's poles exp((-zeta w0 +- j w0 sqrt(1 - zeta^2)) / rate) (the
    sampled oscillator), driven by white noise and scaled to the line's RMS on each axis,
    started from its stationary state (a burn-in of 10 decay times is discarded).  The filter
    state carries over from one block to the next, so the blocks are one stationary series
    however a run is split."""

    def __init__(self, spectrum: VibrationSpectrum, rate_hz: float, rng: np.random.Generator):
        from scipy.signal import lfilter  # here, not at the top: the CLI starts without scipy.signal

        self.rng, self._lfilter = rng, lfilter
        self._lines = []  # (a, per-axis scale, per-axis lfilter state)
        for line in spectrum.lines:
            a1, a2 = line.ar2_coefficients(rate_hz)
            a = np.array([1.0, -a1, -a2])
            burn = int(min(10.0 / (line.damping * 2 * np.pi * line.frequency_hz) * rate_hz, 1e6)) + 2
            # stationary variance of x_k = a1 x_{k-1} + a2 x_{k-2} + e_k with unit-variance e
            unit_var = (1 - a2) / ((1 + a2) * ((1 - a2) ** 2 - a1**2))
            scale = np.array([line.tip_mas, line.tilt_mas]) / np.sqrt(unit_var)
            states = [lfilter([1.0], a, rng.standard_normal(burn), zi=np.zeros(2))[1] for _ in range(2)]
            self._lines.append((a, scale, states))

    def next(self, n_frames: int) -> np.ndarray:
        """The next (n_frames, 2) samples."""
        return self.next_lines(n_frames).sum(axis=0)

    def next_lines(self, n_frames: int) -> np.ndarray:
        """The next (n_lines, n_frames, 2) samples of each line (their sum is ``next``'s; the
        realised RMS of each line in a record, which identification is checked against)."""
        out = np.zeros((len(self._lines), n_frames, 2))
        for i, (a, scale, states) in enumerate(self._lines):
            for axis in range(2):
                x, states[axis] = self._lfilter([1.0], a, self.rng.standard_normal(n_frames), zi=states[axis])
                out[i, :, axis] = x * scale[axis]
        return out
