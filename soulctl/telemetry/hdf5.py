"""Loop telemetry as HDF5 (h5py): what `loop run --telemetry` writes and `optimize gains` reads.

HDF5 because the record is several large arrays of different shapes plus a nested
configuration: one file with named, typed, chunked and compressed datasets and attributes,
read partially by h5py, MATLAB, IDL, Julia or `h5dump` without loading everything, and
extended chunk by chunk while the loop runs (``Hdf5Writer``: constant memory, any length).

Layout (rows are recorded frames; every dataset's "unit" attribute names its unit):
    /slopes            (frames, n_slopes) float32   slopes s(k) from the slope computer (times k)
    /measured_modes    (frames, n_modes)  float32   R s(k), nm
    /commands          (frames, n_actuators) float32  c(k) = Sigma zeta(k), nm
    /command_modes     (frames, n_modes)  float32   M^-1 c(k), nm
    /mirror_modes      (frames, n_modes)  float32   the mirror during frame k (delayed), nm
    /residual_modes    (frames, n_modes)  float32   the simulation's true residual, nm
    /disturbance_modes (frames, n_modes)  float32   the simulation's true disturbance, nm
    /residual_rms_nm   (frames,)          float64
    /frame_counter     (frames,)          int64     the loop's frame number k of each row
    /frame_time_s      (frames,)          float64   k / frame rate
    /sensitivity       (frames,)          float64   slope sensitivity k during frame k
    /flux              (frames,)          float64   detected electrons in frame k
    /gains             (n_modes,)         float64   per-mode gains (Delta of each mode) at the end
    /reconstructor     (n_modes, n_slopes) float32  R: the modes (nm) of the slopes
    /modes_to_commands (n_actuators, n_modes) float32  M: the actuator commands of each mode
    /controller_num    (n_modes, num_terms) float64  each mode's unit-gain time filter, numerator and
    /controller_den    (n_modes, den_terms) float64  denominator in powers of z^-1 (c = g num/den m)
    /gain_history/frames (changes,)       int64     first frame of each gain vector
    /gain_history/gains  (changes, n_modes) float64 the gain vectors in force from those frames
    /aux/<task>/<field> (updates, ...)    float64   auxiliary loops' records (e.g. /aux/ogtl/
                                                    sensitivity, /aux/mgm/gains, /aux/metrics/
                                                    strehl_estimate), /aux/<task>/frame the
                                                    first frame after each update
    attributes: rate_hz, delay_frames, n_modes, sensor, corrector, telescope,
                telescope_diameter_m, telescope_obstruction_m (what the loop is: LBT's
                pyramid and adaptive secondary), soulctl_version, schema_version (2; files
                without it are version 1 and read alike), status (complete | partial |
                writing), partial_reason, telemetry_every (one frame in N recorded),
                diverged_at (-1 if not), configuration (JSON: observation, atmosphere,
                gains, seed, ...), run_description (TOML: the resolved run description;
                `loop run --config this.h5` runs the same loop again)
The per-frame fields are those of `--telemetry-fields` (default: all but slopes and
commands).  A file is written under a temporary name and renamed when the run ends: complete,
or partial (interrupted, diverged, an error) with every frame up to the last one recorded.

``schema.TELEMETRY_SCHEMA`` is this layout as a table - kinds, dtypes, shapes, units and the
range of every value - with the relations between fields (``RELATIONS``); every reader holds a
file to it (``schema.TelemetryReader``) and a test holds this docstring to it.

Offline MGM (`optimize gains --telemetry`) needs measured_modes, command_modes, gains and the
rate_hz and delay_frames attributes; it uses sensitivity, gain_history, /aux/ogtl and the
configuration when present, and reads only the rows of its window (see ``loop.offline``).
"""

from __future__ import annotations

import os
import tomllib
from pathlib import Path

import h5py
import numpy as np

from .. import __version__
from ..errors import InputError
from ..files import atomic_write, commit_or_replace, temporary_beside
from ..ranges import TELEMETRY_SCHEMA_VERSION
from .schema import COMPRESSION, UNITS, TelemetryReader, store, stored

BLOCK_FRAMES = 256  # frames buffered per field before a chunk is written and the file flushed


def write_telemetry(
    path: str | Path, arrays: dict[str, np.ndarray], attributes: dict, configuration: dict, immediate: bool = False
) -> None:
    """A whole telemetry record at once (``telemetry convert``; tests), written atomically."""

    def write(tmp: str) -> None:
        with h5py.File(tmp, "w") as f:
            defaults = {"schema_version": TELEMETRY_SCHEMA_VERSION, "status": "complete", "soulctl_version": __version__}
            store(f, arrays, defaults | attributes | {"configuration": configuration})

    atomic_write(path, write, immediate=immediate)


class Hdf5Writer:
    """A run's telemetry streamed to HDF5 as the loop runs (a ``recorder.Sink``): the chosen
    per-frame fields of one frame in ``every``, buffered ``BLOCK_FRAMES`` at a time, written as
    chunked, compressed datasets and flushed; the gain history and auxiliary records at
    ``finish``.  The file is written under a temporary name beside ``path`` with status
    "writing"; ``finish`` sets "complete" or "partial" (with the reason) and renames it onto
    ``path`` (a complete file at the command's commit, a partial one at once).  A process
    killed outright leaves only the temporary, whose status says "writing"."""

    def __init__(self, path: str | Path, fields: tuple[str, ...], every: int = 1, attributes: dict | None = None):
        self.fields, self.every = tuple(fields), int(every)
        self.target, self.tmp = temporary_beside(path, ".tmp.h5")  # HDF5 whatever the target's format
        self.file = h5py.File(self.tmp, "w")
        self.file.attrs.update(
            {"schema_version": TELEMETRY_SCHEMA_VERSION, "status": "writing", "telemetry_every": self.every}
            | {"soulctl_version": __version__}
            | (attributes or {})
        )
        self.recorder = None
        self.rate_hz = float("nan")  # from ``describe``
        self._buffers: dict[str, np.ndarray] = {}
        self._buffered = self.written = 0

    @property
    def recorded(self) -> int:
        """Frames recorded so far (written or buffered)."""
        return self.written + self._buffered

    def attach(self, recorder) -> None:
        self.recorder = recorder

    def describe(self, attributes: dict, configuration: dict, arrays: dict | None = None) -> None:
        """The loop's static description, known once it is built: rate, delay, modes, the
        configuration and the reconstructor and modal basis (``arrays``)."""
        store(self.file, arrays or {}, attributes | {"configuration": configuration})
        self.rate_hz = float(attributes["rate_hz"])  # kept here: an HDF5 attribute read per frame costs ~20 us
        self.file.flush()

    def append(self, frame: int, values: dict) -> None:
        if frame % self.every:
            return
        if not self._buffers:
            self._create(values)
        i = self._buffered
        for name in self.fields:
            self._buffers[name][i] = values[name]
        self._buffers["frame_counter"][i] = frame
        self._buffers["frame_time_s"][i] = frame / self.rate_hz
        self._buffered = i + 1  # a frame counts once every field holds it
        if self._buffered == BLOCK_FRAMES:
            self._flush()

    def _create(self, values: dict) -> None:
        counters = {"frame_counter": np.int64(0), "frame_time_s": np.float64(0.0)}
        for name in (*self.fields, *counters):
            like = stored(name, values[name] if name in values else counters[name])
            shape = np.shape(like)
            self._buffers[name] = np.zeros((BLOCK_FRAMES, *shape), dtype=like.dtype)
            opts = COMPRESSION if shape and shape[0] * BLOCK_FRAMES > 4096 else {}
            self.file.create_dataset(name, (0, *shape), like.dtype, maxshape=(None, *shape), chunks=(BLOCK_FRAMES, *shape), **opts)
            self.file[name].attrs["unit"] = UNITS.get(name, "")

    def _flush(self) -> None:
        n, m = self.written, self._buffered
        for name, buffer in self._buffers.items():
            ds = self.file[name]
            ds.resize(n + m, axis=0)
            ds[n : n + m] = buffer[:m]
        self.written, self._buffered = n + m, 0
        self.file.flush()

    def finish(self, reason: str | None = None, diverged_at: int = -1) -> None:
        """Write what is buffered, the records of the run, the status (``reason``: why the file
        is partial, None: complete), close, and rename onto the path."""
        self._flush()
        if self.recorder is not None:
            _write_records(self.file, self.recorder)
        self.file.attrs.update({"status": "complete" if reason is None else "partial", "diverged_at": diverged_at})
        if reason is not None:
            self.file.attrs["partial_reason"] = reason
        self.file.close()
        from .formats import read_record, telemetry_format, write_record

        if telemetry_format(self.target) == "hdf5":
            commit_or_replace(self.target, self.tmp, stage=reason is None)
            return
        try:  # AOT FITS or an LBT folder: converted whole from the stream (the recorded fields in memory)
            arrays, attributes = read_record(self.tmp)
            write_record(self.target, arrays, attributes, immediate=reason is not None)
        finally:
            os.unlink(self.tmp)

    def abandon(self) -> None:
        """Close and remove the temporary (a run that recorded nothing worth keeping)."""
        self.file.close()
        os.unlink(self.tmp)


def _write_records(f: h5py.File, recorder) -> None:
    """The gains at the end, the gain history and the auxiliary loops' records."""
    frames, gains = recorder.gain_arrays()
    if len(frames):
        f.create_dataset("gains", data=gains[-1].astype(np.float64))
        f.create_dataset("gain_history/frames", data=frames)
        f.create_dataset("gain_history/gains", data=gains.astype(np.float64))
    for task in recorder.aux:
        for key, value in recorder.aux_arrays(task).items():
            f.create_dataset(f"aux/{task}/{key}", data=value.astype(np.int64) if key == "frame" else value.astype(np.float64))


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
    from .formats import record_of

    with TelemetryReader(path) as tm:
        return record_of(tm)
