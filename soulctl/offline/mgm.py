"""MGM on a recorded telemetry file (`soulctl optimize gains --method mgm --telemetry FILE`):
the gains MGM would apply after the window the file holds, without running a loop.

The file is what `loop run --telemetry` writes (``telemetry.hdf5``) or any HDF5 file with the
fields that module documents; it is held to ``telemetry.schema`` (types, dtypes, shapes, the
relations between fields and the range of every value read).  The window is the file's frames
since the last change of the gains (``/gain_history``) or of the slope sensitivity k
(``/sensitivity``), as live: MGM's model holds for fixed gains and k; at most the last
``MAX_WINDOW_S`` (600 s, the longest period of live MGM).  chi_i comes from the optical-gain
table of the configuration's calibration at the reference correction level of the record's
seeing, as live (the seeing given, else the one the record's run description holds, else the
paper's table seeing, 0.8"; ``plant_seeing``): gamma_i / gamma_p when the file records OGTL
(``/aux/ogtl``: k tracked the optical gain of the probed mode p, ``/aux/ogtl/mode``; 30 in
files that do not record it), gamma_i times the file's k otherwise.

The optimum is the live MGM's, noise rule included (``ModalGainMachine.optimum_of_psd`` of the
window's prewhitened POL PSD).  The gains returned are always a vector `loop run --gains`
accepts: MGM's update (Eq. gainUpdate, from the gains in force during the window, for the
modes whose fall of J is significant, ``ModalGainMachine.significant``; the others keep theirs) capped at
(1 - margin) of each mode's nominal maximum stable gain (chi = 1, the check of `loop run`) with the file's structural
resonance, `loop run`'s default one and none, and at 10 (``ranges.LOOP_GAIN``).  MGM's own
limit, (1 - margin) g_max / chi_i, lies above the nominal one where chi_i < 1; the modes
capped are reported.

Memory: only the fields needed are read, and only over the window: /sensitivity and the tail
of /gain_history/frames (one value per frame at most), one row of /gain_history/gains, /gains,
and /measured_modes and /command_modes in blocks of modes of at most ``BLOCK_BYTES`` (float64)
each, plus the PSDs (n_modes x (segment / 2 + 1)).  A window of one block (the usual case) is
read once; a larger one is read twice, checked before the calibration, used after it.

Refused with exit status 2, naming the field: a file that is not a regular HDF5 file, a
missing field, a field of the wrong type, shape or range (NaN and infinite values included),
fields that disagree, a mode count, frame rate or delay that differs from the configuration's,
a loop that diverged, recorded gains outside 0..10, measured modes without signal (constant
over the window), a window shorter than 4 PSD segments of 64 frames (the minimum duration is
given), an OGTL that never calibrated k (``check_ogtl_calibrated``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import defaults
from ..control import mgm
from ..control.delay import fractional_taps
from ..control.filters import Filter
from ..control.gains import DEFAULT_FORGETTING, unit_loops
from ..control.ogtl import HELD, PROBE_MODE, STATUS
from ..control.structure import StructuralResonance, sampled_coefficients
from ..errors import InputError
from ..loop.chi_model import mgm_chi, optical_gain_table
from ..loop.run import calibration_for
from ..loop.schedule import welch_settings
from ..observation import Observation
from ..optics.cache import ArrayCache
from ..optics.optical_gains import CHI_TABLE_SEEING_ARCSEC
from ..ranges import LOOP_GAIN, PERIOD_S
from ..run_config import ControllerSpec, RunConfig, stored
from ..telemetry.figures import pseudo_open_loop
from ..telemetry.formats import check_decimation, open_telemetry, run_description_of
from ..telemetry.schema import REQUIRED, TelemetryReader, configuration_member, configuration_observation, configuration_structure
from .recorded import RecordedLoop, checked_rate, recorded_loop

MAX_WINDOW_S = PERIOD_S.hi  # the longest window of live MGM
BLOCK_BYTES = 32 * 2**20  # float64 bytes of one block of modes of /measured_modes (and as many of /command_modes)


REASONS = {  # why MGM's gain of a mode is not its optimum (OfflineMgmResult.reasons)
    "step": "Eq. gainUpdate: a step of rho from the recorded gain towards nu x the optimum",
    "bounded": "the step bounded at a factor 2 of the recorded gain (MgmSettings.max_change)",
    "not significant": "the fall of J within its noise: the recorded gain kept",
    "capped": "capped at the nominal stability limit (chi = 1, as loop run checks)",
}


@dataclass
class OfflineMgmResult:
    path: str
    rate_hz: float
    delay_frames: float
    previous_gains: np.ndarray  # in force during the window (from /gain_history, else /gains)
    optimum: np.ndarray  # g_hat_i (step 4)
    gains: np.ndarray  # what MGM would apply (step 5)
    chi: np.ndarray
    ogtl: bool
    sensitivity: float
    first_frame: int
    frames: int  # frames of the window
    segment: int  # Welch segment (frames)
    reasons: tuple[str, ...] = ()  # per mode, why the gain is not the optimum (REASONS)
    probe_mode: int | None = None  # the mode OGTL probed (chi_i = gamma_i / gamma_probe), None without OGTL
    chi_from: str = ""  # where gamma_i came from: the pyramid's model (at a seeing), --chi-table, or the sensor's 1
    chi_seeing_arcsec: float | None = None  # the seeing of the optical-gain table, None with gamma given
    chi_seeing_from: str = ""  # where that seeing came from
    notes: tuple[str, ...] = ()  # what the record's loop is and what was assumed (recorded.RecordedLoop)

    @property
    def n_modes(self) -> int:
        return len(self.gains)

    @property
    def capped(self) -> tuple[int, ...]:
        """Modes (1-based) whose MGM gain was capped at the nominal limit."""
        return tuple(i + 1 for i, r in enumerate(self.reasons) if r == "capped")

    def to_dict(self) -> dict:
        window = {"first_frame": self.first_frame, "frames": self.frames, "seconds": self.frames / self.rate_hz}
        return {
            "telemetry": self.path,
            "rate_hz": self.rate_hz,
            "delay_frames": self.delay_frames,
            "window": window | {"welch_segment": self.segment},
            "ogtl": self.ogtl,
            "probe_mode": self.probe_mode,
            "sensitivity": self.sensitivity,
            "chi": self.chi.tolist(),
            "chi_from": self.chi_from,
            "chi_seeing_arcsec": self.chi_seeing_arcsec,
            "chi_seeing_from": self.chi_seeing_from,
            "previous_gains": self.previous_gains.tolist(),
            "optimum": self.optimum.tolist(),
            "gains": self.gains.tolist(),
            "reasons": list(self.reasons),
            "reason_legend": REASONS,
            "capped_modes": list(self.capped),
            "notes": list(self.notes),
        }


def filter_limits(filters: Sequence[Filter], delay_frames: float, rate_hz: float, structures: Sequence, margin: float) -> np.ndarray:
    """Per mode, (1 - margin) of the maximum stable gain of its filter at chi = 1 (the check of
    `loop run`), the least over ``structures`` ((b, a) or None) on Tip/Tilt, at most LOOP_GAIN.hi."""
    ones = np.ones(len(filters))
    limits = np.min([mgm.gain_limits(filters, ones, delay_frames, rate_hz, margin, s) for s in structures], axis=0)
    return np.minimum(limits, LOOP_GAIN.hi)


def nominal_limits(observation: Observation, structure: StructuralResonance | None, margin: float) -> np.ndarray:
    """``filter_limits`` of the observation's filters with ``structure``, `loop run`'s default
    resonance and none (each as the rate samples it)."""
    rate = observation.frame_rate_hz
    unit, _ = unit_loops(observation, None, DEFAULT_FORGETTING, observation.modes)
    return filter_limits(unit, observation.delay_frames, rate, resonances(rate, structure, StructuralResonance()), margin)


def resonances(rate_hz: float, *structures: StructuralResonance | None) -> list:
    """The distinct (b, a) of the structures the rate samples, and None (no resonance)."""
    return list({sampled_coefficients(s, rate_hz) for s in (*structures, None)})


def reasons_of(
    previous: np.ndarray, optimum: np.ndarray, stepped: np.ndarray, moves: np.ndarray, capped: np.ndarray, settings: mgm.MgmSettings
) -> tuple[str, ...]:
    """Per mode, why the gain MGM applies is not its optimum (the keys of REASONS)."""
    free = (1.0 - settings.rho) * np.asarray(previous) + settings.rho * settings.nu * np.asarray(optimum)
    out = []
    for i in range(len(free)):
        if capped[i]:
            out.append("capped")
        elif not moves[i]:
            out.append("not significant")
        elif not np.isclose(stepped[i], free[i], rtol=1e-12, atol=0.0):
            out.append("bounded")
        else:
            out.append("step")
    return tuple(out)


def window_start(tm: TelemetryReader, frames: int, first: int) -> tuple[int, np.ndarray | None, np.ndarray | None]:
    """(start, k over frames first.., the gains in force from start or None): the window
    starts at the file's last gains and k, after the last entry of /gain_history/frames below
    ``frames`` and after the last change of /sensitivity, and not before ``first``.  Reads
    /sensitivity from ``first`` and the tail of /gain_history/frames that can matter."""
    start = first
    k = None
    if tm.has("sensitivity"):
        k = tm.read("sensitivity", slice(first, frames))
        moved = np.flatnonzero(np.diff(k) != 0)
        if len(moved):
            start = max(start, first + int(moved[-1]) + 1)
    if not tm.has("gain_history/frames"):
        return start, k, None
    # strictly increasing frames in 0..frames: at most frames - first + 1 entries from first on,
    # and the one before them may be in force at start
    changes = tm.dim("changes")
    lo = max(0, changes - (frames - first + 2))
    history = tm.read("gain_history/frames", slice(lo, changes))
    inside = history[history < frames]
    if len(inside):
        start = max(start, int(inside.max()))
    before = np.flatnonzero(history <= start)
    if not len(before):
        return start, k, None
    row = lo + int(before[-1])
    return start, k, tm.read("gain_history/gains", slice(row, row + 1))[0]


def mode_blocks(n_modes: int, frames: int) -> list[slice]:
    """Blocks of modes of at most BLOCK_BYTES over ``frames`` (at least 2 modes: the first
    block holds Tip and Tilt, which the structural resonance couples)."""
    width = max(2, BLOCK_BYTES // (8 * max(1, frames)))
    return [slice(lo, min(n_modes, lo + width)) for lo in range(0, n_modes, width)]


def _window_data(tm: TelemetryReader, rows: slice, blocks: list[slice], keep: bool, path: str | Path) -> list:
    """Read and check /measured_modes and /command_modes over the window, block by block;
    the blocks' data if ``keep`` (else []).  InputError for modes whose measurement is constant."""
    kept, flat = [], []
    for cols in blocks:
        measured = tm.read("measured_modes", rows, cols)
        commands = tm.read("command_modes", rows, cols)
        flat += (np.flatnonzero(np.ptp(measured, axis=0) == 0) + cols.start + 1).tolist()
        if keep:
            kept.append((measured, commands))
    if flat:
        more = f" and {len(flat) - 1} more" if len(flat) > 1 else ""
        raise InputError(
            f"telemetry file {path}: field measured_modes has no signal in mode {flat[0]}{more} (constant over "
            f"the window of {rows.stop - rows.start} frames): MGM needs the loop's measurements of every mode"
        )
    return kept


def recorded_probe_mode(tm: TelemetryReader, n_modes: int, path: str | Path) -> int | None:
    """The mode OGTL probed (``/aux/ogtl/mode`` at its last update; 1-based), or PROBE_MODE in
    files written before it was recorded: MGM's chi_i = gamma_i / gamma_probe needs it (a run
    made with --probe-mode 10 read as mode 30 got the wrong chi for every mode).  None in a file
    without OGTL (no ``/aux/ogtl``); InputError if its OGTL never calibrated k
    (``check_ogtl_calibrated``)."""
    if not len(tm.group("aux/ogtl") or ()):
        return None
    check_ogtl_calibrated(tm, path)
    ds = tm.dataset("aux/ogtl/mode")
    if ds is None or ds.shape[:1] == (0,):
        return PROBE_MODE
    last = np.asarray(ds[-1], dtype=float) if np.issubdtype(ds.dtype, np.number) else np.array([math.nan])
    mode = float(last.reshape(-1)[0]) if last.size == 1 else math.nan
    if not (math.isfinite(mode) and mode == round(mode) and 1 <= mode <= n_modes):
        raise InputError(f"telemetry file {path}: /aux/ogtl/mode must hold the probed mode, an integer in 1..{n_modes}, got {mode:g}")
    return int(mode)


def check_ogtl_calibrated(tm: TelemetryReader, path: str | Path) -> None:
    """InputError if the file's OGTL never acted on an estimate (``/aux/ogtl/status`` all held:
    probe SNR below the threshold, commands growing or no estimate): its k was not calibrated,
    so chi_i = gamma_i / gamma_probe, MGM's plant with OGTL, does not hold and the loop's optical
    gain is unknown within OGTL's k_max - the live optimisers wait for a calibrated k for the
    same reason (``loop.optimize``); InputError too for statuses that are not OGTL's (integers
    in 0..len(STATUS) - 1).  Files that do not record the status pass."""
    ds = tm.dataset("aux/ogtl/status")
    if ds is None or ds.size == 0:
        return
    status = np.asarray(ds[...], dtype=float).reshape(-1) if np.issubdtype(ds.dtype, np.number) else np.array([math.nan])
    if not np.all(np.isin(status, np.arange(len(STATUS)))):
        raise InputError(f"telemetry file {path}: /aux/ogtl/status must hold OGTL's update statuses, integers in 0..{len(STATUS) - 1}")
    held = np.isin(status, sorted(HELD))
    if held.all():
        raise InputError(
            f"telemetry file {path}: OGTL never acted on a reliable estimate ({status.size} updates, all held), so k was not "
            "calibrated and the loop's optical gain is unknown; record a run in which OGTL calibrates k"
        )


def recorded_run(tm: TelemetryReader, observation: Observation | None, path: str | Path) -> RunConfig:
    """The run a telemetry file records: its stored run description, else (files written
    before soulctl stored one) what its configuration attribute holds, which is checked in
    either case; ``observation``, when given, replaces the file's."""
    conf = tm.configuration()
    # a soulctl record without the field ran the sampled one; another system's, SOUL's field
    field = defaults.PREDATED_WFS_FIELD_ARCSEC if conf else defaults.WFS_FIELD_ARCSEC
    recorded = RunConfig(
        observation=observation or configuration_observation(conf, path),
        oversampling=configuration_member(conf, "oversampling", 2, path),
        wfs_field_arcsec=configuration_member(conf, "field_of_view_arcsec", field, path),
        controller=ControllerSpec(forgetting=configuration_member(conf, "gains.forgetting", DEFAULT_FORGETTING, path)),
        structure=configuration_structure(conf, path),
    )
    if tm.has("run_description"):
        recorded = RunConfig.from_dict(stored(run_description_of(tm)), f"telemetry file {path}")
    return recorded if observation is None else dataclasses.replace(recorded, observation=observation)


@dataclass(frozen=True)
class PlantInputs:
    """What offline MGM takes from options where the record lacks it or is to be overridden:
    the loop delay (frames), the optical gains gamma_i (``optics gains --out`` CSV) and the
    structural resonance (``recorded.STRUCTURE_CHOICES``)."""

    delay_frames: float | None = None
    optical_gains: np.ndarray | None = None
    resonance: str = "auto"


def own_record(tm: TelemetryReader) -> bool:
    """A soulctl record: it stores its run (a run description or a configuration's observation)."""
    return tm.has("run_description") or "observation" in tm.configuration()


def _check_recording(tm: TelemetryReader, n_modes: int, config: RunConfig | None, path: str | Path) -> None:
    """A stable loop's record whose modes and frame rate are the configuration's (InputError
    naming the field)."""
    diverged = tm.attribute("diverged_at", -1)
    if diverged >= 0:
        raise InputError(f"telemetry file {path} records a loop that diverged (frame {diverged}): MGM needs a stable loop's telemetry")
    if config is None:
        return
    expected = config.observation.modes
    if n_modes != expected:
        raise InputError(
            f"telemetry file {path}: field measured_modes has shape ({tm.dim('frames')}, {n_modes}), expected "
            f"(frames, {expected}) for the configuration's {expected} modes"
        )
    checked_rate(tm.attribute("rate_hz"), config.observation.frame_rate_hz, path)


def _loop_delay(tm: TelemetryReader, config: RunConfig | None, given: float | None, path: str | Path) -> float:
    """The delay given, else the record's (which must be the configuration's), else the
    configuration's, else InputError saying how to give one."""
    if given is not None:
        return given
    recorded = tm.attribute("delay_frames", None)
    if config is None:
        if recorded is None:
            raise tm.lacks(["delay_frames"], "MGM's pseudo-open loop")
        return recorded
    expected = config.observation.delay_frames
    if recorded is not None and abs(recorded - expected) > 1e-6:
        raise InputError(
            f"telemetry file {path}: attribute delay_frames is {recorded:g} frames but the configuration's delay is "
            f"{expected:g} frames at {config.observation.frame_rate_hz:g} Hz"
        )
    return expected if recorded is None else recorded


def _optical_gains(
    tm: TelemetryReader, loop: RecordedLoop, config: RunConfig | None, plant: PlantInputs, cache: ArrayCache, seeing_given: float | None
) -> tuple:
    """(gamma_i, where from, the table's seeing or None, where that came from): given; the
    pyramid's model for a pyramid (from the configuration's calibration); 1 for another sensor."""
    if plant.optical_gains is not None:
        return plant.optical_gains, "given (--chi-table)", None, "--chi-table"
    if loop.sensor != "pyramid":
        what = f"a {loop.sensor}" if loop.sensor != "unknown" else "not stated"
        return np.ones(len(loop.filters)), f"1: the record's sensor is {what}, not a pyramid (--chi-table gives others)", None, ""
    if config is None:
        raise InputError(
            f"telemetry file {tm.path}: the record's sensor is a pyramid, whose optical gains need the pyramid's model: "
            "give --config or --mag (the observation), or --chi-table"
        )
    seeing, seeing_from = plant_seeing(tm, config, seeing_given)
    gamma = optical_gain_table(calibration_for(config.request(), cache), cache, seeing)
    return gamma, f"the pyramid's model (optics gains) at {seeing:g}\" seeing: {seeing_from}", seeing, seeing_from


def plant_seeing(tm: TelemetryReader, description: RunConfig, given: float | None) -> tuple[float, str]:
    """The seeing of MGM's optical-gain table and where it comes from: ``given``, else the
    seeing the record's run description holds, else the paper's table seeing (0.8").  Why the
    record's: gamma falls from 0.39 to 0.24 to 0.15 between 0.6, 0.8 and 1.0" (R11 flux, 10x10,
    54 modes); MGM designing for 0.8" a loop that ran at 0.6" over-drives it by 1.6x, past
    the PWFS's linear range (docs/physics.md, offline MGM)."""
    if given is not None:
        return given, "given"
    if tm.has("run_description"):
        return description.atmosphere.seeing_arcsec, "the record's run description"
    return CHI_TABLE_SEEING_ARCSEC, "the paper's table seeing (the record holds none)"


def offline_mgm(
    path: str | Path,
    observation: Observation | None = None,
    cache: ArrayCache = ArrayCache(None),
    settings: mgm.MgmSettings | None = None,
    chi_seeing_arcsec: float | None = None,
    plant: PlantInputs = PlantInputs(),
) -> OfflineMgmResult:
    """MGM's gains for the window of the telemetry file ``path`` (see the module).
    ``observation``: the configuration to check the file against (default: the file's own;
    another system's record needs none but for a pyramid's optical gains);
    ``chi_seeing_arcsec``: the optical-gain table's seeing (default: ``plant_seeing``);
    ``plant``: a delay, optical gains or resonance given instead of the record's and the model's."""
    with open_telemetry(path, tuple(n for n in REQUIRED if n != "delay_frames")) as tm:
        check_decimation(tm, path, "MGM's spectra")
        description = recorded_run(tm, observation, path) if own_record(tm) else None
        config = description or (RunConfig(observation=observation) if observation is not None else None)
        n_modes = tm.dim("n_modes")
        _check_recording(tm, n_modes, config, path)
        loop = recorded_loop(tm, description, n_modes, plant.resonance)
        delay, rate = _loop_delay(tm, config, plant.delay_frames, path), loop.rate_hz
        recorded = tm.read("gains")  # the gains at the end, checked even when the history gives the window's
        frames = tm.dim("frames")
        first = max(0, frames - round(MAX_WINDOW_S * rate))
        start, k, previous = window_start(tm, frames, first)
        previous = recorded if previous is None else previous
        n, _ = fractional_taps(delay)
        window = frames - start
        settings = settings or welch_settings(window, rate, "the telemetry window after the last change of gains or k", dropped=n + 1)
        if window <= n + 1:  # only with ``settings`` given: welch_settings refuses short windows
            raise InputError(f"telemetry file {path}: the window after the last change of gains or k holds {window} frames")
        sensitivity = float(k[start - first]) if k is not None else 1.0
        rows = slice(start, frames)
        blocks = mode_blocks(n_modes, window)
        data = _window_data(tm, rows, blocks, len(blocks) == 1, path)  # checked before the calibration
        probe_mode = recorded_probe_mode(tm, n_modes, path)
        gamma, chi_from, seeing, seeing_from = _optical_gains(tm, loop, config, plant, cache, chi_seeing_arcsec)
        chi = mgm_chi(gamma, True, probe_mode) if probe_mode is not None else gamma * sensitivity
        machine = mgm.ModalGainMachine(loop.filters, chi, loop.model_delay(delay), rate, settings, loop.structure_ba)
        psd = []
        for i, cols in enumerate(blocks):
            measured, commands = data[i] if data else _window_data(tm, rows, [cols], True, path)[0]
            pol = pseudo_open_loop(measured / chi[cols], commands, delay, machine.structure if cols.start == 0 else None)
            psd.append(machine.pol_psd(pol[n + 1 :], cols))
    psd_all = np.concatenate(psd)
    optimum, _ = machine.optimum_of_psd(psd_all)
    moves = machine.significant(psd_all, previous, optimum, [mgm.segments_of(window - n - 1, settings)])
    stepped = mgm.update_gains(previous, optimum, settings, moves)
    others = (description.structure, StructuralResonance()) if description is not None else (loop.structure,)
    limits = filter_limits(loop.filters, loop.model_delay(delay), rate, resonances(rate, *others), settings.margin)
    reasons = reasons_of(previous, optimum, stepped, moves, stepped > limits, settings)
    window_info = (start, window, settings.segment)
    return OfflineMgmResult(
        str(path), rate, delay, previous, optimum, np.minimum(stepped, limits), chi, probe_mode is not None, sensitivity, *window_info,
        reasons, probe_mode, chi_from, seeing, seeing_from, loop.notes,
    )  # fmt: skip
