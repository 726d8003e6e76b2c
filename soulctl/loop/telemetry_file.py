"""Loop telemetry as HDF5 (h5py): what `loop run --telemetry` writes and `optimize gains` reads.

HDF5 because the record is several large arrays of different shapes plus a nested
configuration: one file with named, typed, chunked and compressed datasets and attributes,
read partially by h5py, MATLAB, IDL, Julia or `h5dump` without loading everything.

Layout (rows are frames):
    /slopes            (frames, n_slopes) float32   slopes s(k) from the slope computer
    /measured_modes    (frames, n_modes)  float32   R s(k), nm
    /commands          (frames, n_actuators) float32  c(k) = Sigma zeta(k), nm
    /command_modes     (frames, n_modes)  float32   M^-1 c(k), nm
    /mirror_modes      (frames, n_modes)  float32   the mirror during frame k (delayed), nm
    /residual_modes    (frames, n_modes)  float32   the simulation's true residual, nm
    /disturbance_modes (frames, n_modes)  float32   the simulation's true disturbance, nm
    /residual_rms_nm   (frames,)          float64
    /frame_time_s      (frames,)          float64   k / frame rate
    /sensitivity       (frames,)          float64   slope sensitivity k during frame k
    /flux              (frames,)          float64   detected electrons in frame k
    /gains             (n_modes,)         float64   per-mode gains (Delta of each mode) at the end
    /gain_history/frames (changes,)       int64     first frame of each gain vector
    /gain_history/gains  (changes, n_modes) float64 the gain vectors in force from those frames
    /aux/<task>/<field> (updates, ...)    float64   auxiliary loops' records (e.g. /aux/ogtl/
                                                    sensitivity, /aux/mgm/gains, /aux/metrics/
                                                    strehl_estimate), /aux/<task>/frame the
                                                    first frame after each update
    attributes: rate_hz, delay_frames, n_modes, soulctl_version, diverged_at (-1 if not),
                configuration (JSON: observation, atmosphere, gains, seed, ...),
                run_description (TOML: the resolved run description; `loop run --config
                this.h5` runs the same loop again)
The file is written to a temporary name and renamed (never half-written).

``telemetry_schema.TELEMETRY_SCHEMA`` is this layout as a table - kinds, dtypes, shapes, units
and the range of every value - with the relations between fields (``RELATIONS``); every reader
holds a file to it (``telemetry_schema.TelemetryReader``) and a test holds this docstring to it.

Offline MGM (`optimize gains --telemetry`) needs measured_modes, command_modes, gains and the
rate_hz and delay_frames attributes; it uses sensitivity, gain_history, /aux/ogtl and the
configuration when present, and reads only the rows of its window (see ``loop.offline``).
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import h5py
import numpy as np

from .. import __version__
from ..errors import InputError
from ..files import atomic_write
from .telemetry_schema import ATTRIBUTES, DATASETS, FLOAT32, TelemetryReader


def telemetry_arrays(telemetry) -> dict[str, np.ndarray]:
    """The datasets of a ``simulation.Telemetry``: per-frame records, frame times, the gain
    history and the auxiliary loops' records (names with '/' become HDF5 groups)."""
    arrays = telemetry.arrays()
    arrays["frame_time_s"] = np.arange(len(arrays["residual_rms_nm"])) / telemetry.rate_hz
    frames, gains = telemetry.gain_arrays()
    arrays["gain_history/frames"] = frames.astype(np.int64)
    arrays["gain_history/gains"] = gains
    for task in telemetry.aux:
        for key, value in telemetry.aux_arrays(task).items():
            arrays[f"aux/{task}/{key}"] = value.astype(np.int64) if key == "frame" else value
    return arrays


def write_telemetry(path: str | Path, arrays: dict[str, np.ndarray], attributes: dict, configuration: dict) -> None:
    def write(tmp: str) -> None:
        with h5py.File(tmp, "w") as f:
            for name, data in arrays.items():
                data = np.asarray(data)
                if data.dtype.kind != "i":
                    data = data.astype(np.float32 if name in FLOAT32 else np.float64)
                opts = {"compression": "gzip", "compression_opts": 1, "chunks": True} if data.ndim == 2 and data.size > 4096 else {}
                f.create_dataset(name, data=data, **opts)
            for k, v in attributes.items():
                f.attrs[k] = v
            f.attrs["soulctl_version"] = __version__
            f.attrs["configuration"] = json.dumps(configuration)

    atomic_write(path, write)


def stored_run_description(path: str | Path) -> dict:
    """The run description stored in a telemetry file (``run_config.RunConfig.from_dict``
    reads it); InputError when the file has none."""
    with TelemetryReader(path) as tm:
        return run_description_of(tm)


def run_description_of(tm: TelemetryReader) -> dict:
    """The stored run description of an open telemetry file, as a dict."""
    text = tm.attribute("run_description", None)
    if text is None:
        raise InputError(f"telemetry file {tm.path} holds no run description (written by `loop run` before soulctl stored one)")
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"telemetry file {tm.path}: attribute run_description is not TOML ({e})") from None


def read_telemetry(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """(arrays, attributes with the configuration decoded) of every field of the schema the
    file holds, each checked against it (``TelemetryReader``); InputError naming the field
    otherwise.  The whole file is read into memory (offline MGM reads only its window)."""
    with TelemetryReader(path) as tm:
        names = [f.name for f in DATASETS if tm.has(f.name)]
        aux = tm.group("aux")
        for task in aux or ():
            names += [f"aux/{task}/{key}" for key in tm.group(f"aux/{task}") or ()]
        arrays = {name: tm.read(name) for name in names}
        attrs = {f.name: tm.attribute(f.name) for f in ATTRIBUTES if f.name != "configuration" and tm.has(f.name)}
        if tm.has("configuration"):
            attrs["configuration"] = tm.configuration()
    return arrays, attrs
