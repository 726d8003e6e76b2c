"""The part of a telemetry record that identification reads, as spectra.

The window is the record's last stretch at fixed gains (the frames after the last change, as
offline MGM takes them: the loop's transfer functions hold only there) over which the slope
sensitivity k stays within ``K_SPREAD`` of its final value (OGTL changes k every period; once
it has settled, k chi, the loop's gain, is steady), at most ``MAX_WINDOW_S``.  For every mode
the Welch PSD of the measurement m/k (k divided out: m/k = chi (phi - mirror) + n), which
the rejection fit reads, and the lagged moments of m/k and of the commands c (M^-1 c, probe
included), from which the pseudo-open loop's variance follows for any delay and optical gain
(``pol_variance``) without a second read.  The rows are read once, in blocks of ``ROW_BLOCK`` frames with every
mode (the files are chunked by frames: blocks of modes decompressed every chunk once per
block, 7x the time); memory holds one block, the spectra and the Tip/Tilt and probe series.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.fft
from numpy.typing import ArrayLike

from ..control.filters import Filter
from ..control.transfer import Plant
from ..errors import InputError
from ..offline.mgm import recorded_run
from ..offline.recorded import RecordedLoop, recorded_loop
from ..ranges import DELAY_FRAMES
from ..run_config import RunConfig
from ..telemetry.formats import check_decimation, open_telemetry
from ..telemetry.schema import TelemetryReader

MAX_WINDOW_S = 600.0
MIN_WINDOW_S = 1.0  # shorter windows are refused: a few Welch segments of ~0.25 s
K_SPREAD = 0.1  # k within 10 % of its final value
SEGMENT_S = 0.25  # Welch segment of the loop spectra (~4 Hz resolution)
ROW_BLOCK = 8192  # frames read at a time (all modes: 16 MB of float32 at 500 modes)
NEEDED = ("measured_modes", "command_modes", "gains", "rate_hz")
DELAY_SPAN = 1.5  # frames searched on either side of the record's delay
UNKNOWN_DELAY_FRAMES = (0.0, 6.0)  # searched when the record states none (AO loops: 1-5 frames)


def delay_search(delay_frames: float) -> tuple[float, float]:
    """The delays the rejection fit searches: the record's +- DELAY_SPAN, else UNKNOWN_DELAY_FRAMES."""
    if not math.isfinite(delay_frames):
        return UNKNOWN_DELAY_FRAMES
    return max(0.0, delay_frames - DELAY_SPAN), delay_frames + DELAY_SPAN


@dataclass(frozen=True)
class Probe:
    """The OGTL probe the record holds: its mode (1-based) and frequency."""

    mode: int
    frequency_hz: float


@dataclass
class LoopRecord:
    """A record's window as identification reads it (see the module)."""

    path: str
    rate_hz: float
    delay_frames: float  # the record's (or the configuration's): the starting point, not the answer
    description: RunConfig | None
    loop: RecordedLoop  # each mode's unit-gain controller, the structural resonance, the pupil's Tip/Tilt scale
    gains: np.ndarray  # in force during the window
    sensitivity: float  # k at the end of the window (m is divided by each frame's k)
    f_hz: np.ndarray
    p_m: np.ndarray  # (n_modes, F) PSD of m/k, nm^2/Hz
    moments: np.ndarray  # (n_modes, 3 + lags): var m/k, var c, cov(c(k), c(k-1)), cov(m/k(k), c(k-j)) j = 0..lags-1
    half_moments: tuple[np.ndarray, np.ndarray]  # ``moments`` of the window's first and second halves
    tip_tilt: tuple[np.ndarray, np.ndarray]  # (frames, 2) of m/k and of c, from ``tip_tilt_first_frame``
    probe: Probe | None
    probe_series: tuple[np.ndarray, np.ndarray] | None  # m/k and c of the probed mode
    first_frame: int
    frames: int
    segments: int  # independent Welch segments (frames / segment)
    tip_tilt_first_frame: int  # Tip/Tilt is kept from the last change of the gains (k need not have settled)

    @property
    def n_modes(self) -> int:
        return self.p_m.shape[0]

    @property
    def filters(self) -> tuple[Filter, ...]:
        return self.loop.filters

    @property
    def structure_ba(self) -> tuple | None:
        """The Tip/Tilt structural resonance (b, a) at this rate, None without one."""
        return self.loop.structure_ba


def _description(tm: TelemetryReader, path: str | Path) -> RunConfig | None:
    try:
        return recorded_run(tm, None, path)
    except InputError:
        if tm.has("run_description") or "observation" in tm.configuration():
            raise
        return None  # a foreign record: integrators at the recorded gains


def _probe(tm: TelemetryReader, rate: float) -> Probe | None:
    modes, frequencies = tm.dataset("aux/ogtl/mode"), tm.dataset("aux/ogtl/frequency_hz")
    if modes is None or frequencies is None or modes.shape[:1] == (0,):
        return None
    mode = int(np.asarray(modes[-1]).reshape(-1)[0])
    f = float(np.asarray(frequencies[-1]).reshape(-1)[0])
    if not (1 <= mode <= tm.dim("n_modes") and math.isfinite(f) and 0 < f < 0.5 * rate):
        raise InputError(f"telemetry file {tm.path}: /aux/ogtl holds probe mode {mode} at {f:g} Hz, not a probe of this record")
    return Probe(mode, f)


def _window(tm: TelemetryReader, frames: int, first: int) -> tuple[int, int, np.ndarray | None, np.ndarray]:
    """(gains' start, start, k over frames from the gains' start, the gains in force): after
    the last change of the gains (/gain_history), and from ``start`` on k within K_SPREAD of
    its final value."""
    start, gains = first, None
    if tm.has("gain_history/frames") and tm.dim("changes"):
        changes = tm.read("gain_history/frames")
        inside = np.flatnonzero(changes < frames)
        if len(inside):
            start = max(start, int(changes[inside[-1]]))
            gains = tm.read("gain_history/gains", slice(int(inside[-1]), int(inside[-1]) + 1))[0]
    k, settled = None, start
    if tm.has("sensitivity"):
        k = tm.read("sensitivity", slice(start, frames)).astype(float)
        apart = np.flatnonzero(np.abs(k / k[-1] - 1.0) > K_SPREAD)
        settled = start + (int(apart[-1]) + 1 if len(apart) else 0)
    return start, settled, k, np.asarray(tm.read("gains") if gains is None else gains, dtype=float)


def read_record(path: str | Path, delay_frames: float | None = None, structure: str = "auto") -> LoopRecord:
    """The window of the record at ``path`` as spectra (see the module); InputError for a
    record identification cannot use (decimated, diverged, shorter than ``MIN_WINDOW_S``);
    ``structure``: ``recorded.STRUCTURE_CHOICES``."""
    if delay_frames is not None:
        DELAY_FRAMES.check(delay_frames, "delay_frames")
    with open_telemetry(path, NEEDED) as tm:
        check_decimation(tm, path, "the identification's spectra")
        if tm.attribute("diverged_at", -1) >= 0:
            raise InputError(f"telemetry file {path} records a loop that diverged: identification needs a stable loop")
        description = _description(tm, path)
        n_modes, frames = tm.dim("n_modes"), tm.dim("frames")
        loop = recorded_loop(tm, description, n_modes, structure)
        rate = loop.rate_hz
        delay = delay_frames if delay_frames is not None else tm.attribute("delay_frames", None)
        if delay is None:
            delay = description.observation.delay_frames if description else math.nan
        first = max(0, frames - round(MAX_WINDOW_S * rate))
        gains_start, start, k, gains = _window(tm, frames, first)
        sensitivity = float(k[-1]) if k is not None else 1.0
        window = frames - start
        if window < MIN_WINDOW_S * rate:
            raise InputError(
                f"telemetry file {path}: nothing can be identified from {window} frames ({window / rate:.3g} s) at fixed gains "
                f"and k: the spectra need at least {MIN_WINDOW_S:g} s ({math.ceil(MIN_WINDOW_S * rate)} frames at {rate:g} Hz); "
                "record a longer stretch at fixed gains (loop run without --mgm/--ogtl, --duration of 2 s or more)"
            )
        segment = 2 ** int(round(math.log2(SEGMENT_S * rate)))
        lags = int(math.ceil(delay_search(delay)[1] + 0.5)) + 2
        probe = _probe(tm, rate)
        stats = _Accumulator(n_modes, segment, lags, probe.mode - 1 if probe else None, window // 2)
        before: list[tuple[np.ndarray, np.ndarray]] = []  # Tip/Tilt while k settled: the lines' longer window
        for lo in range(gains_start, frames, ROW_BLOCK):
            hi = min(frames, lo + ROW_BLOCK)
            m = tm.read("measured_modes", slice(lo, hi)).astype(float)
            if k is not None:
                m /= k[lo - gains_start : hi - gains_start, None]
            c = tm.read("command_modes", slice(lo, hi)).astype(float)
            split = min(max(start - lo, 0), hi - lo)
            before.append((m[:split, :2].copy(), c[:split, :2].copy()))  # copies: a view would keep the block
            if split < hi - lo:
                stats.add(m[split:], c[split:])
    f, p_m = stats.spectrum(rate)
    tt_m, tt_c = (x.reshape(len(x), -1) for x in stats.series(0, min(2, n_modes)))  # (frames, 2), or 1 for a one-mode record
    tt = (np.concatenate([x[0] for x in before] + [tt_m]), np.concatenate([x[1] for x in before] + [tt_c]))
    return LoopRecord(
        str(path), rate, float(delay), description, loop, gains, sensitivity, f, p_m, stats.moments(), stats.half_moments(),
        tt, probe, stats.series(probe.mode - 1, probe.mode) if probe else None, start, window, window // segment, gains_start,
    )  # fmt: skip


class _Accumulator:
    """The Welch PSD of m/k (Hann, half-overlapping segments, each segment's mean removed:
    scipy's ``welch`` defaults) and the lagged moments of m/k and c, fed
    row block after row block (every row read once: the files are chunked by frames), and
    the Tip/Tilt and probed mode's series."""

    def __init__(self, n_modes: int, segment: int, lags: int, probe_column: int | None, half: int):
        self.segment, self.hop, self.lags = segment, segment // 2, lags
        self.half = half
        self.at_half: tuple[np.ndarray, int] = (np.zeros(0), 0)  # the sums over the window's first ``half`` frames
        from scipy.signal import get_window  # here, not at the top: the CLI starts without scipy.signal

        self.window = get_window("hann", segment)
        self.carry_m = np.zeros((0, n_modes))  # the rows of m the next segment starts in
        F = segment // 2 + 1
        self.pm, self.count = np.zeros((F, n_modes)), 0
        self.sums = np.zeros((5 + lags, n_modes))  # sum m, sum c, sum m^2, sum c^2, sum c(k)c(k-1), sum m(k)c(k-j)
        self.n = 0
        self.last_c = np.zeros((0, n_modes))
        self.columns = sorted({0, 1} & set(range(n_modes)) | ({probe_column} if probe_column is not None else set()))
        self.kept: list[tuple[np.ndarray, np.ndarray]] = []

    def add(self, m: np.ndarray, c: np.ndarray) -> None:
        self._moments(m, c)
        self.kept.append((m[:, self.columns].copy(), c[:, self.columns].copy()))
        m = np.concatenate([self.carry_m, m])
        starts = range(0, len(m) - self.segment + 1, self.hop)
        if len(starts):
            idx = np.asarray(starts)[:, None] + np.arange(self.segment)[None, :]
            self.pm += np.sum(np.abs(self._fft(m[idx])) ** 2, axis=0)
            self.count += len(starts)
        nxt = starts[-1] + self.hop if len(starts) else 0
        self.carry_m = m[nxt:]

    def _fft(self, seg: np.ndarray) -> np.ndarray:
        seg -= seg.mean(axis=1, keepdims=True)  # a copy already (fancy indexing)
        seg *= self.window[None, :, None]
        return scipy.fft.rfft(seg, axis=1, workers=-1)

    def _moments(self, m: np.ndarray, c: np.ndarray) -> None:
        cut = self.half - self.n
        if 0 < cut < len(m):  # the block spans the window's middle: the first half's sums are kept at it
            self._moments(m[:cut], c[:cut])
            self._moments(m[cut:], c[cut:])
            return
        cc = np.concatenate([self.last_c, c])  # c with the rows before this block, for the lags
        off = len(self.last_c)
        s = self.sums
        s[0] += m.sum(axis=0)
        s[1] += c.sum(axis=0)
        s[2] += np.einsum("ij,ij->j", m, m)
        s[3] += np.einsum("ij,ij->j", c, c)
        s[4] += np.einsum("ij,ij->j", cc[off:], cc[off - 1 : -1]) if off else np.einsum("ij,ij->j", c[1:], c[:-1])
        for j in range(self.lags):
            lo = max(0, j - off)  # rows of m whose c(k - j) exists
            s[5 + j] += np.einsum("ij,ij->j", m[lo:], cc[off + lo - j : off + len(m) - j])
        self.n += len(m)
        self.last_c = cc[-self.lags :]
        if self.n == self.half:
            self.at_half = (s.copy(), self.n)

    def spectrum(self, rate: float) -> tuple[np.ndarray, np.ndarray]:
        scale = 1.0 / (rate * np.sum(self.window**2) * max(1, self.count))
        double = np.ones(self.segment // 2 + 1)
        double[1 : -1 if self.segment % 2 == 0 else None] = 2.0
        w = (scale * double)[:, None]
        f = np.fft.rfftfreq(self.segment, 1.0 / rate)
        return f, (self.pm * w).T

    def moments(self) -> np.ndarray:
        """As the rows of ``pol_variance`` need them: var m, var c, cov c(k)c(k-1), cov m(k)c(k-j)."""
        return self._moments_of(self.sums, self.n)

    def half_moments(self) -> tuple[np.ndarray, np.ndarray]:
        """``moments`` of the window's first and second halves (the second's lagged products
        at its start reach into the first: a few frames in thousands)."""
        first, n = self.at_half
        if n == 0:  # a window of one frame
            return self.moments(), self.moments()
        return self._moments_of(first, n), self._moments_of(self.sums - first, self.n - n)

    def _moments_of(self, s: np.ndarray, n: int) -> np.ndarray:
        mean_m, mean_c = s[0] / n, s[1] / n
        out = [s[2] / n - mean_m**2, s[3] / n - mean_c**2, s[4] / n - mean_c**2]
        out += [s[5 + j] / n - mean_m * mean_c for j in range(self.lags)]
        return np.stack(out, axis=1)

    def series(self, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        cols = [self.columns.index(i) for i in range(lo, hi)]
        m = np.concatenate([x[0][:, cols] for x in self.kept])
        c = np.concatenate([x[1][:, cols] for x in self.kept])
        return (m, c) if hi - lo > 1 else (m[:, 0], c[:, 0])


def pol_variance(record: LoopRecord, delay_frames: float, chi: np.ndarray, moments: np.ndarray | None = None) -> np.ndarray:
    """Variance of m/(k chi) + (1 - e) c(k - n) + e c(k - n - 1) per mode (without the
    structural resonance: Tip/Tilt's variance is the vibrations' and turbulence's, at low
    frequencies where the resonance does not act), over the window or from ``moments`` (one
    of ``record.half_moments``)."""
    n = int(math.floor(delay_frames + 1e-12))
    e = delay_frames - n
    mo = record.moments if moments is None else moments
    if n + 4 > mo.shape[1]:
        raise ValueError(f"delay {delay_frames:g} beyond the lags recorded")
    x = 1.0 / np.asarray(chi, dtype=float)
    var_dc = ((1 - e) ** 2 + e**2) * mo[:, 1] + 2 * e * (1 - e) * mo[:, 2]
    cross = (1 - e) * mo[:, 3 + n] + e * mo[:, 4 + n]
    return x**2 * mo[:, 0] + var_dc + 2 * x * cross


def plant_response(record: LoopRecord, delay_frames: float, tip_tilt: bool, f_hz: ArrayLike) -> np.ndarray:
    """The mirror's response to the commands at f_hz: z^-d as the delay line interpolates it,
    times 1 + G on Tip/Tilt (``transfer.Plant`` with chi = 1, the structure where the record has it)."""
    plant = Plant(delay_frames, 1.0, record.structure_ba if tip_tilt else None)
    return plant.frequency_response(2.0 * np.pi * np.asarray(f_hz, dtype=float) / record.rate_hz)
