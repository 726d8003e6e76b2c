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
    /gains             (n_modes,)         float64   per-mode gains (Delta of each mode)
    attributes: rate_hz, delay_frames, n_modes, soulctl_version, diverged_at (-1 if not),
                configuration (JSON: observation, atmosphere, gains, seed, ...)
The file is written to a temporary name and renamed (never half-written).
"""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from .. import __version__
from ..errors import InputError
from ..files import atomic_write

FLOAT32 = ("slopes", "measured_modes", "commands", "command_modes", "mirror_modes", "residual_modes", "disturbance_modes")
REQUIRED = ("measured_modes", "command_modes", "gains")


def write_telemetry(path: str | Path, arrays: dict[str, np.ndarray], attributes: dict, configuration: dict) -> None:
    def write(tmp: str) -> None:
        with h5py.File(tmp, "w") as f:
            for name, data in arrays.items():
                data = np.asarray(data, dtype=np.float32 if name in FLOAT32 else np.float64)
                opts = {"compression": "gzip", "compression_opts": 1, "chunks": True} if data.ndim == 2 and data.size > 4096 else {}
                f.create_dataset(name, data=data, **opts)
            for k, v in attributes.items():
                f.attrs[k] = v
            f.attrs["soulctl_version"] = __version__
            f.attrs["configuration"] = json.dumps(configuration)

    atomic_write(path, write)


def read_telemetry(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """(arrays, attributes with the configuration decoded); InputError if the file is not a
    telemetry file (missing fields named)."""
    try:
        with h5py.File(path, "r") as f:
            missing = [k for k in REQUIRED if k not in f]
            if missing or "rate_hz" not in f.attrs or "delay_frames" not in f.attrs:
                need = missing + [a for a in ("rate_hz", "delay_frames") if a not in f.attrs]
                raise InputError(f"telemetry file {path} lacks {', '.join(need)}")
            arrays = {k: f[k][()] for k in f.keys()}
            attrs = {k: (v.item() if hasattr(v, "item") else v) for k, v in f.attrs.items()}
    except (OSError, KeyError) as e:
        raise InputError(f"cannot read telemetry file {path}: {e}") from None
    if "configuration" in attrs:
        attrs["configuration"] = json.loads(attrs["configuration"])
    return arrays, attrs
