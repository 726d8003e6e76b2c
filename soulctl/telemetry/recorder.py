"""What the simulated loop keeps of its telemetry while it runs, at constant memory.

Per frame the loop produces every record of the schema (``schema.PER_FRAME``): slopes, R s,
commands, their modes, the mirror's modes, the true residual and disturbance modes, the
residual RMS, k and the flux.  ``TelemetryRecorder`` keeps of them only what live consumers
need and hands each frame to a sink (``sinks``: an HDF5 file written in chunks as the loop
runs, or memory for tests and the Python API):

* ring buffers of the auxiliary loops' window fields (R s, M^-1 c, the mirror's modes, slopes,
  flux), sized by the longest window asked for (``keep_window``): an auxiliary loop reads at
  most its period;
* the run's metrics series, a few numbers per frame (Tip/Tilt of the residual, of R s and of
  M^-1 c; residual RMS; k; flux: 72 bytes a frame, 0.12 MB per simulated second at 1700 Hz)
  and the running mean and variance of the residual modes from a chosen frame on;
* the gain history and the auxiliary loops' records (one row per update or change).

A run without a sink therefore holds nothing per frame beyond those buffers and series, and
its peak memory does not grow with the run's length but by the series' 72 bytes a frame.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

WINDOW_FIELDS = ("measured_modes", "command_modes", "mirror_modes", "slopes", "flux")
# Tip/Tilt (the first two modes) of these records are kept for the whole run (the metrics).
TIP_TILT_SERIES = {"residual_tt": "residual_modes", "measured_tt": "measured_modes", "command_tt": "command_modes"}
SCALAR_SERIES = ("residual_rms_nm", "sensitivity", "flux")


class Sink(Protocol):
    """Where the frames' records go (``sinks``); ``attach`` gives it the recorder, whose gain
    history and auxiliary records it writes when it closes."""

    def attach(self, recorder: TelemetryRecorder) -> None: ...

    def append(self, frame: int, values: dict) -> None: ...


class Series:
    """A growing array of rows (capacity doubles; a view of the filled rows)."""

    def __init__(self, width: int = 0, dtype=np.float64):
        self._data = np.zeros((1024, width) if width else 1024, dtype=dtype)
        self.n = 0

    def append(self, row) -> None:
        if self.n == len(self._data):
            self._data = np.concatenate([self._data, np.zeros_like(self._data)])
        self._data[self.n] = row
        self.n += 1

    @property
    def values(self) -> np.ndarray:
        return self._data[: self.n]


class Ring:
    """The last ``capacity`` rows of a per-frame field."""

    def __init__(self, like: np.ndarray, capacity: int):
        self.capacity = capacity
        self._data = np.zeros((capacity, *np.shape(like)), dtype=np.asarray(like).dtype)

    def put(self, frame: int, row) -> None:
        self._data[frame % self.capacity] = row

    def rows(self, start: int, stop: int) -> np.ndarray:
        """Rows of frames start..stop-1 (a copy, in order); they must be among the last kept."""
        return self._data[np.arange(start, stop) % self.capacity]

    def resized(self, capacity: int, frames: int) -> Ring:
        """A ring of ``capacity`` rows holding what this one holds of the last frames."""
        ring = Ring(self._data[0], capacity)
        start = max(0, frames - min(self.capacity, capacity))
        for k in range(start, frames):
            ring.put(k, self._data[k % self.capacity])
        return ring


class ModalMoments:
    """Running mean and (population) variance of the modes from frame ``start`` on (Welford)."""

    def __init__(self, start: int = 0):
        self.start, self.n = start, 0
        self.mean: np.ndarray | None = None
        self._m2: np.ndarray | None = None

    def add(self, frame: int, modes: np.ndarray) -> None:
        if frame < self.start:
            return
        x = np.asarray(modes, dtype=np.float64)
        if self.mean is None or self._m2 is None:
            self.mean, self._m2 = np.zeros_like(x), np.zeros_like(x)
        self.n += 1
        delta = x - self.mean
        self.mean += delta / self.n
        self._m2 += delta * (x - self.mean)

    @property
    def variance(self) -> np.ndarray | None:
        return None if self._m2 is None or self.n == 0 else self._m2 / self.n


class TelemetryRecorder:
    """The live telemetry of a loop (see the module); ``sink``: where every frame goes."""

    def __init__(self, rate_hz: float, sink: Sink | None = None):
        self.rate_hz, self.sink = rate_hz, sink
        self.frames = 0
        self.window_frames = 0  # rows kept of each window field
        self._rings: dict[str, Ring] = {}
        self._series = {name: Series(2) for name in TIP_TILT_SERIES} | {name: Series() for name in SCALAR_SERIES}
        self.residual_moments = ModalMoments()
        self.gain_history: list[tuple[int, np.ndarray]] = []  # (first frame, gains in force)
        self.aux: dict[str, list[dict]] = {}  # task -> [{"frame": f, ...}], f the first frame after the update
        if sink is not None:
            sink.attach(self)

    def keep_window(self, frames: int) -> None:
        """Keep at least the last ``frames`` frames of the window fields from now on."""
        if frames > self.window_frames:
            self.window_frames = frames
            self._rings = {name: ring.resized(frames, self.frames) for name, ring in self._rings.items()}

    def moments_from(self, frame: int) -> None:
        """Accumulate the residual modes' mean and variance from ``frame`` on (afresh)."""
        self.residual_moments = ModalMoments(frame)

    def append_frame(self, **values) -> None:
        """One frame's records (every per-frame field of the schema)."""
        k = self.frames
        if self.window_frames:
            for name in WINDOW_FIELDS:
                if name not in self._rings:
                    self._rings[name] = Ring(np.asarray(values[name]), self.window_frames)
                self._rings[name].put(k, values[name])
        for name, source in TIP_TILT_SERIES.items():
            self._series[name].append(values[source][:2])
        for name in SCALAR_SERIES:
            self._series[name].append(values[name])
        self.residual_moments.add(k, values["residual_modes"])
        if self.sink is not None:
            self.sink.append(k, values)
        self.frames = k + 1

    def rows(self, name: str, start: int, stop: int) -> np.ndarray:
        """Rows of window field ``name`` for frames start..stop-1 (the last ``window_frames``)."""
        if stop > start and (start < self.frames - self.window_frames or name not in self._rings):
            raise ValueError(f"frames {start}..{stop - 1} of {name} are no longer kept (the last {self.window_frames} are)")
        return self._rings[name].rows(start, stop) if name in self._rings else np.zeros((0,))

    def series(self, name: str) -> np.ndarray:
        """A metrics series of the whole run (``TIP_TILT_SERIES``, ``SCALAR_SERIES``)."""
        return self._series[name].values

    residual_rms_nm = property(lambda self: self.series("residual_rms_nm"))
    sensitivity = property(lambda self: self.series("sensitivity"))

    def arrays(self) -> dict[str, np.ndarray]:
        """Every frame's records, from a ``MemorySink`` (other sinks keep them elsewhere)."""
        if not isinstance(self.sink, MemorySink):
            raise ValueError("the whole run's records are kept only with a MemorySink")
        return self.sink.arrays()

    def aux_arrays(self, name: str) -> dict[str, np.ndarray]:
        """One auxiliary loop's records as arrays (rows = updates)."""
        records = self.aux.get(name, [])
        return {key: np.asarray([r[key] for r in records]) for key in (records[0] if records else {})}

    def gain_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(frames where gains were set, (changes, n_modes) gains)."""
        return np.array([f for f, _ in self.gain_history], dtype=np.int64), np.array([g for _, g in self.gain_history])


class MemorySink:
    """Every frame's records kept in memory (tests; short runs from the Python API):
    ``arrays()`` gives them whole, rows = frames.  Memory grows with the run."""

    def __init__(self) -> None:
        self._rows: dict[str, list] = {}

    def attach(self, recorder: TelemetryRecorder) -> None:
        pass

    def append(self, frame: int, values: dict) -> None:
        for name, value in values.items():
            self._rows.setdefault(name, []).append(np.copy(value))

    def arrays(self) -> dict[str, np.ndarray]:
        return {name: np.asarray(rows) for name, rows in self._rows.items()}
