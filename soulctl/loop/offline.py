"""MGM on a recorded telemetry file (`soulctl optimize gains --method mgm --telemetry FILE`):
the gains MGM would apply after the window the file holds, without running a loop.

The file is what `loop run --telemetry` writes (``telemetry_file``) or any HDF5 file with the
fields that module documents.  The window is the file's frames since the last change of the
gains (``/gain_history``) or of the slope sensitivity k (``/sensitivity``), as live: MGM's
model holds for fixed gains and k.  chi_i comes from the optical-gain table of the
configuration's calibration at the reference correction level, as live: gamma_i / gamma_30 when
the file records OGTL (``/aux/ogtl``: k tracked the optical gain of mode 30), gamma_i times the
file's k otherwise.

Refused with exit status 2, naming the field: a missing field, NaN or infinite values, a mode
count that differs from the configuration's, a loop that diverged, a window shorter than 4
PSD segments of 64 frames (the minimum duration is given).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..control import mgm
from ..control.delay import fractional_taps
from ..control.ogtl import PROBE_MODE
from ..control.structure import StructuralResonance
from ..errors import InputError
from ..observation import Observation
from ..optics.cache import ArrayCache
from .metrics import pseudo_open_loop
from .optimize import mgm_chi, mgm_machine, optical_gain_table, welch_settings
from .run import RunRequest, calibration_for
from .simulation import DEFAULT_FORGETTING
from .telemetry_file import read_telemetry

PER_FRAME = ("measured_modes", "command_modes")


@dataclass
class OfflineMgmResult:
    path: str
    observation: Observation
    previous_gains: np.ndarray  # in force during the window (from /gain_history, else /gains)
    optimum: np.ndarray  # g_hat_i (step 4)
    gains: np.ndarray  # what MGM would apply (step 5)
    chi: np.ndarray
    ogtl: bool
    sensitivity: float
    first_frame: int
    frames: int  # frames of the window
    segment: int  # Welch segment (frames)

    def to_dict(self) -> dict:
        return {
            "telemetry": self.path,
            "window": {"first_frame": self.first_frame, "frames": self.frames,
                       "seconds": self.frames / self.observation.frame_rate_hz, "welch_segment": self.segment},
            "ogtl": self.ogtl,
            "sensitivity": self.sensitivity,
            "previous_gains": self.previous_gains.tolist(),
            "optimum": self.optimum.tolist(),
            "gains": self.gains.tolist(),
        }


def _finite(arrays: dict, name: str, path) -> np.ndarray:
    data = np.asarray(arrays[name], dtype=float)
    if not np.all(np.isfinite(data)):
        bad = int(np.sum(~np.isfinite(data)))
        raise InputError(f"telemetry file {path}: field {name} has {bad} NaN or infinite values")
    return data


def window_start(arrays: dict, frames: int) -> int:
    """First frame at the file's last gains and k: after the last entry of
    /gain_history/frames and after the last change of /sensitivity."""
    start = 0
    changes = arrays.get("gain_history/frames")
    if changes is not None and len(changes):
        start = max(start, int(np.max(changes[changes < frames], initial=0)))
    k = arrays.get("sensitivity")
    if k is not None and len(k) == frames:
        moved = np.flatnonzero(np.diff(np.asarray(k, dtype=float)) != 0)
        if len(moved):
            start = max(start, int(moved[-1]) + 1)
    return start


def _configuration(attrs: dict, observation: Observation | None, path) -> tuple[Observation, dict]:
    conf = attrs.get("configuration")
    if conf is not None and not isinstance(conf, dict):
        raise InputError(f"telemetry file {path}: attribute configuration must be a JSON object")
    if observation is None:
        if not conf or "observation" not in conf:
            raise InputError(f"telemetry file {path} lacks the configuration attribute (observation); give --config or --mag")
        try:
            observation = Observation.from_dict(conf["observation"])
        except (TypeError, KeyError, AttributeError, ValueError) as e:
            raise InputError(f"telemetry file {path}: attribute configuration.observation is not an observation ({e})") from None
    return observation, conf or {}


def _structure(conf: dict, path) -> StructuralResonance | None:
    d = conf.get("structure")
    if not d:
        return None
    try:
        return StructuralResonance(**d)
    except (TypeError, ValueError) as e:
        raise InputError(f"telemetry file {path}: attribute configuration.structure is not a resonance ({e})") from None


def _forgetting(conf: dict, path) -> float:
    gains = conf.get("gains", {})
    value = gains.get("forgetting", DEFAULT_FORGETTING) if isinstance(gains, dict) else None
    if not isinstance(value, (int, float)) or not 0 <= value <= 1:
        raise InputError(f"telemetry file {path}: attribute configuration.gains.forgetting must be a number in 0..1")
    return float(value)


def window_gains(arrays: dict, start: int, final: np.ndarray) -> np.ndarray:
    """The gains in force from frame ``start`` on: the last /gain_history entry at or before
    it (the file's /gains are those at the end, possibly set after the last frame)."""
    frames, gains = arrays.get("gain_history/frames"), arrays.get("gain_history/gains")
    if frames is None or gains is None or not len(frames):
        return final
    before = np.flatnonzero(np.asarray(frames) <= start)
    return np.asarray(gains[before[-1]], dtype=float) if len(before) else final


def offline_mgm(path, observation: Observation | None = None, cache: ArrayCache = ArrayCache(None),
                settings: mgm.MgmSettings | None = None, chi_seeing_arcsec: float = 0.8) -> OfflineMgmResult:
    """MGM's gains for the window of the telemetry file ``path`` (see the module).
    ``observation``: the configuration to check the file against (default: the file's own)."""
    arrays, attrs = read_telemetry(path)
    observation, conf = _configuration(attrs, observation, path)
    if int(attrs.get("diverged_at", -1)) >= 0:
        raise InputError(f"telemetry file {path} records a loop that diverged (frame {attrs['diverged_at']}): MGM needs a stable loop's telemetry")
    data = {name: _finite(arrays, name, path) for name in (*PER_FRAME, "gains")}
    for name in ("sensitivity",):
        if name in arrays:
            data[name] = _finite(arrays, name, path)
    n_modes = observation.modes
    for name in PER_FRAME:
        if data[name].ndim != 2 or data[name].shape[1] != n_modes:
            raise InputError(f"telemetry file {path}: field {name} has shape {data[name].shape}, expected (frames, {n_modes}) "
                             f"for the configuration's {n_modes} modes")
    if data["gains"].shape != (n_modes,):
        raise InputError(f"telemetry file {path}: field gains has {data['gains'].size} values, the configuration controls {n_modes} modes")
    frames = data["measured_modes"].shape[0]
    if data["command_modes"].shape[0] != frames:
        raise InputError(f"telemetry file {path}: field command_modes has {data['command_modes'].shape[0]} frames, measured_modes {frames}")
    rate = float(attrs["rate_hz"])
    if abs(rate - observation.frame_rate_hz) > 1e-6 * rate:
        raise InputError(f"telemetry file {path}: attribute rate_hz is {rate:g} Hz but the configuration runs at {observation.frame_rate_hz:g} Hz")
    start = window_start(arrays, frames)
    delay = float(attrs["delay_frames"])
    n, _ = fractional_taps(delay)
    window = frames - start
    settings = settings or welch_settings(window, rate, "the telemetry window after the last change of gains or k", dropped=n + 1)
    k = float(data["sensitivity"][start]) if "sensitivity" in data else 1.0
    ogtl = any(name.startswith("aux/ogtl/") for name in arrays)
    run = RunRequest(observation, oversampling=int(conf.get("oversampling", 2)))
    calibration = calibration_for(run, cache)
    gamma = optical_gain_table(calibration, cache, chi_seeing_arcsec)
    chi = mgm_chi(gamma, ogtl, PROBE_MODE) if ogtl else gamma * k
    structure = _structure(conf, path)
    forgetting = _forgetting(conf, path)
    machine = mgm_machine(observation, structure, chi, settings, forgetting, delay)
    measured = data["measured_modes"][start:]
    pol = pseudo_open_loop(measured / chi, data["command_modes"][start:], delay, machine.structure)
    optimum, _ = machine.optimum(pol[n + 1 :])
    previous = window_gains(arrays, start, data["gains"])
    if previous.shape != (n_modes,) or not np.all(np.isfinite(previous)):
        raise InputError(f"telemetry file {path}: field gain_history/gains does not hold {n_modes} finite gains per entry")
    gains = mgm.update_gains(previous, optimum, settings)
    return OfflineMgmResult(str(path), observation, previous, optimum, gains, chi, ogtl, k, start, window, settings.segment)
