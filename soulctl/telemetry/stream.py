"""The run's telemetry as it is recorded: frames streamed into an HDF5 temporary beside the
target (``hdf5``'s layout, chunk by chunk: constant memory, any length), then renamed onto an
HDF5 target or converted whole into AOT FITS or an LBT folder (``formats``)."""

from __future__ import annotations

import os
from pathlib import Path

import h5py
import numpy as np

from .. import __version__
from ..files import commit_or_replace, temporary_beside
from ..ranges import TELEMETRY_SCHEMA_VERSION
from .formats import read_record, telemetry_format, write_record
from .schema import COMPRESSION, UNITS, store, stored

BLOCK_FRAMES = 256  # frames buffered per field before a chunk is written and the file flushed


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
