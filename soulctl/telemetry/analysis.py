"""What `soulctl telemetry inspect` and `telemetry psd` compute; they read the model only
(``schema.TelemetryReader``, whichever format it came from)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..control.mgm import noise_floor
from ..errors import InputError
from ..optics.pupil import LBT_DIAMETER_M, LBT_OBSTRUCTION, Pupil
from .figures import JITTER_EDGE_HZ, RESOLUTION_HZ, pseudo_open_loop, tip_tilt_jitter
from .schema import DATASETS, TelemetryReader, nested

TIP_TILT = (1, 2)  # 1-based modes


def frame_steps(tm: TelemetryReader) -> tuple[int, int, int]:
    """(decimation, gaps, lost frames) from the frame counter, as LBT's elab_lib counts them:
    decimation = median step - 1, a gap a step beyond decimation + 1 (aoframes_counter:51-56);
    (0, 0, 0) without a counter."""
    if not tm.has("frame_counter") or tm.dim("frames") < 2:
        return 0, 0, 0
    steps = np.diff(tm.read("frame_counter"))
    if np.any(steps <= 0):
        raise InputError(f"telemetry file {tm.path}: field frame_counter must increase from row to row")
    decimation = int(np.median(steps)) - 1
    gaps = steps > decimation + 1
    return decimation, int(gaps.sum()), int(np.sum(steps[gaps] // (decimation + 1) - 1))


def inspect(tm: TelemetryReader, kind: str) -> dict:
    """The record's description: format, status, rate, frames, duration, decimation and gaps,
    fields with their shapes and units, modes, the auxiliary loops, the run description, what
    the record says of its system (sensor, corrector, telescope) and its reader's notes."""
    rate = tm.attribute("rate_hz", None)
    frames = tm.dims.get("frames", (0,))[0]
    decimation, gaps, lost = frame_steps(tm)
    fields = {}
    for f in DATASETS:
        ds = tm.dataset(f.name) if tm.has(f.name) else None
        if ds is not None:
            fields[f.name] = {"shape": list(ds.shape), "unit": tm.unit(f.name)}
    span = int(tm.read("frame_counter", slice(frames - 1, frames))[0]) + 1 if tm.has("frame_counter") and frames else frames
    conf = tm.configuration()
    return {
        "format": kind,
        "status": tm.attribute("status", "complete"),
        "partial_reason": tm.attribute("partial_reason", None),
        "rate_hz": rate,
        "delay_frames": tm.attribute("delay_frames", None),
        "frames": frames,
        "duration_s": span / rate if rate else None,
        "decimation": decimation,
        "gaps": gaps,
        "lost_frames": lost,
        "modes": tm.dims.get("n_modes", (None,))[0],
        "fields": fields,
        "auxiliary_loops": sorted(tm.group("aux") or ()),
        "run_description": tm.has("run_description"),
        "sensor": tm.attribute("sensor", None),
        "corrector": tm.attribute("corrector", None),
        "telescope": tm.attribute("telescope", None),
        "telescope_diameter_m": tm.attribute("telescope_diameter_m", None),
        "notes": [{"field": n.field or None, "note": n.text} for n in tm.notes],
        "star_magnitude_r": nested(conf, "observation", "star", "magnitude_r", number=True),
        "seeing_arcsec": nested(conf, "seeing_arcsec", number=True),
        "seed": nested(conf, "seed", number=True),
    }


@dataclass(frozen=True)
class ModalSpectra:
    """Over the record's window: Welch PSDs (nm^2/Hz) of the chosen modes' records, each
    record's white noise floor per mode, the Tip/Tilt jitter of each record (``figures``: the
    definition `loop run` reports) and what the record does not resolve (``warnings``)."""

    f_hz: np.ndarray
    modes: tuple[int, ...]  # 1-based
    psd: dict  # record -> (n_modes, n_freq)
    jitter: dict  # record -> figures.Jitter (with modes 1 and 2)
    window: tuple[int, int]  # the rows analysed: [first, stop)
    floor: dict = field(default_factory=dict)  # record -> (n_modes,) white noise floor, nm^2/Hz (``control.mgm.noise_floor``)
    nm_per_mas: float = 1.0  # the record's pupil's Tip/Tilt scale
    warnings: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()

    def tip_tilt_jitter(self) -> dict:
        """Per record, the Tip/Tilt jitter per axis (mas) over the whole band and above
        JITTER_EDGE_HZ (``figures.Jitter``), as measured and with the white noise floor
        removed, and the floor's share; None above the edge when the window does not resolve it."""
        out = {}
        for name, j in self.jitter.items():
            floor = float(self.floor[name][[self.modes.index(1), self.modes.index(2)]].mean())
            nyquist = j.f_hz[-1] + j.resolution_hz / 2
            row: dict[str, float | None] = {"resolution_hz": j.resolution_hz}
            for label, value, start in (("all", j.total, 0.0), ("above_3hz", j.above(), JITTER_EDGE_HZ)):
                if value is None:
                    row |= {label: None, f"{label}_floor_removed": None, f"{label}_noise_floor": None}
                    continue
                first = float(j.f_hz[int(np.searchsorted(j.f_hz, start))]) if start else 0.0
                noise = floor * (nyquist - first) / self.nm_per_mas**2
                row[label] = value
                row[f"{label}_floor_removed"] = math.sqrt(max(value**2 - noise, 0.0))
                row[f"{label}_noise_floor"] = math.sqrt(noise)
            out[name] = row
        return out


PUPIL_PIXELS = 160  # the Tip/Tilt scale's pupil sampling (within 0.1 % of the continuous pupil's)


def nm_per_mas_tip_tilt(diameter_m: float = LBT_DIAMETER_M, obstruction_m: float | None = None) -> float:
    """nm RMS of the unit-RMS Tip mode per mas of tilt on a pupil of this diameter and central
    obstruction (LBT's by default, as ``stages.Disturbance``)."""
    fraction = LBT_OBSTRUCTION if obstruction_m is None else obstruction_m / diameter_m
    if not (diameter_m > 0 and 0 <= fraction < 1):
        raise InputError(f"a telescope's obstruction must be smaller than its diameter, got {obstruction_m} and {diameter_m} m")
    return Pupil(PUPIL_PIXELS, diameter_m, fraction).nm_per_mas_tilt()


def nm_per_mas_of(tm: TelemetryReader) -> tuple[float, str | None]:
    """The Tip/Tilt scale of the record's pupil (``nm_per_mas_tip_tilt``) and, where the record
    states no telescope, LBT's: a soulctl record's (written before records stated it), or
    another system's with a note saying so."""
    diameter = tm.attribute("telescope_diameter_m", None)
    simulated = nested(tm.configuration(), "tip_tilt_nm_per_mas", number=True) if tm.has("configuration") else None
    if simulated is not None and simulated > 0:  # a soulctl run's: the scale of its own sampled pupil
        return float(simulated), None
    if diameter is None and (tm.has("soulctl_version") or tm.has("configuration")):
        return nm_per_mas_tip_tilt(), None
    if diameter is None or diameter <= 0:
        return nm_per_mas_tip_tilt(), f"the record states no telescope diameter: Tip/Tilt in mas on LBT's pupil ({LBT_DIAMETER_M:g} m)"
    return nm_per_mas_tip_tilt(diameter, tm.attribute("telescope_obstruction_m", 0.0)), None


def spectra(tm: TelemetryReader, modes: tuple[int, ...], pseudo_open: bool, delay_frames: float | None = None) -> ModalSpectra:
    """PSDs of measured (R s), command (M^-1 c), the simulation's true residual (where the
    record holds it) and, with ``pseudo_open``, pseudo-open-loop modes (the delay given, else
    the record's), over the record's window (``record_window``); the rows must be consecutive
    frames (no decimation, no gap)."""
    rate = tm.attribute("rate_hz")
    decimation, gaps, _ = frame_steps(tm)
    if decimation or gaps:
        raise InputError(f"telemetry file {tm.path}: the frames are decimated ({decimation}) or have gaps ({gaps}): PSDs need every frame")
    n_modes = tm.dims.get("n_modes", (0,))[0]
    bad = [m for m in modes if not 1 <= m <= n_modes]
    if bad:
        raise InputError(f"--modes: mode {bad[0]} is not in 1..{n_modes} (the record's modes)")
    first, stop = record_window(tm)
    names = ("measured_modes", "command_modes", "residual_modes")
    records = {name: _columns(tm, name, modes, stop) for name in names if tm.has(name)}
    if pseudo_open:
        missing = [n for n in ("measured_modes", "command_modes") if n not in records]
        if missing:
            raise InputError(f"telemetry file {tm.path} lacks {missing[0]}: the pseudo-open loop needs measured and command modes")
        if delay_frames is None and not tm.has("delay_frames"):
            raise tm.lacks(["delay_frames"], "the pseudo-open loop")
        delay = tm.attribute("delay_frames") if delay_frames is None else delay_frames
        records["pseudo_open_loop"] = pseudo_open_loop(records["measured_modes"], records["command_modes"], delay)
    if not records:
        raise InputError(f"telemetry file {tm.path} lacks measured_modes and command_modes: nothing to analyse")
    records = {name: x[first:] for name, x in records.items()}
    frames = next(iter(records.values())).shape[0]
    if frames < 16:
        raise InputError(f"telemetry file {tm.path} holds {frames} frames in its window: PSDs need at least 16")
    # ~1 Hz resolution where the record allows, else segments of half the record (3 averages)
    nperseg = min(2 ** int(np.ceil(np.log2(rate / RESOLUTION_HZ))), 2 ** int(np.log2(frames / 2)))
    from scipy.signal import welch  # here, not at the top: the CLI starts without scipy.signal

    scale, note = nm_per_mas_of(tm)
    psd, jitter, floor = {}, {}, {}
    for name, x in records.items():
        f, p = welch(x, fs=rate, nperseg=nperseg, axis=0, detrend="constant")
        psd[name], floor[name] = p.T, noise_floor(p.T, f, rate)
        if all(m in modes for m in TIP_TILT):
            j = tip_tilt_jitter(x[:, [modes.index(1), modes.index(2)]], rate, scale)
            if j is not None:
                jitter[name] = j
    resolution = next(iter(jitter.values())).resolution_hz if jitter else f[1] - f[0]
    warnings = _resolution_warnings(frames, rate, resolution)
    return ModalSpectra(f, modes, psd, jitter, (first, first + frames), floor, scale, warnings, (note,) if note else ())


def record_window(tm: TelemetryReader) -> tuple[int, int]:
    """The rows [first, stop) whose figures a record gives: after the frames its run left out
    while the loop closed (a soulctl run's ``skipped_frames``; none for another system's
    record), up to the frame its loop diverged at (after it they hold anything)."""
    frames = tm.dim("frames")
    diverged = tm.attribute("diverged_at", -1)
    stop = frames if diverged < 0 else min(diverged, frames)
    skipped = nested(tm.configuration(), "skipped_frames", number=True)
    first = int(skipped) if skipped is not None and 0 <= skipped < stop else 0
    return first, stop


def _resolution_warnings(frames: int, rate: float, df: float) -> tuple[str, ...]:
    """What a record too short for the spectra's resolution cannot tell, in one line each."""
    out = []
    if df > RESOLUTION_HZ * 1.01:
        out.append(
            f"a record of {frames / rate:.3g} s gives a {df:.3g} Hz resolution "
            f"({RESOLUTION_HZ:g} Hz needs {2 / RESOLUTION_HZ:g} s): lines closer than {df:.3g} Hz are not resolved"
        )
    if df > JITTER_EDGE_HZ:
        out.append(f"the jitter band's {JITTER_EDGE_HZ:g} Hz edge is below the {df:.3g} Hz resolution: the figures above it are left out")
    return tuple(out)


def _columns(tm: TelemetryReader, name: str, modes: tuple[int, ...], stop: int) -> np.ndarray:
    """The modes' columns of the rows before ``stop``."""
    return np.column_stack([tm.read(name, slice(0, stop), slice(m - 1, m)) for m in modes]).astype(float)
