"""The telemetry formats soulctl reads and writes, chosen by the path: a folder (or a new path
ending in '/' or named Data_<TN>) is an LBT tracking-number folder (``lbt``), a .fits/.fit/.fts
file AOT FITS (``aot``), anything else soulctl's HDF5 (``hdf5``).  Every reader returns the model (``schema.TelemetryReader``: the
schema's fields, checked); analyses read only the model."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import input_file
from .schema import ATTRIBUTES, DATASETS, REQUIRED, TelemetryReader

FITS_SUFFIXES = (".fits", ".fit", ".fts")
HDF5_SUFFIXES = (".h5", ".hdf5", ".he5")
FORMATS = ("hdf5", "aot", "lbt")


def telemetry_format(path: str | Path) -> str:
    """'lbt' for a folder, 'aot' for a FITS suffix, 'hdf5' for an HDF5 suffix or another
    existing file; a new path ending in '/' or named Data_<...> (LBT's folder names) is 'lbt',
    anything else 'hdf5'."""
    p = Path(path)
    if p.is_dir():
        return "lbt"
    if p.suffix.lower() in FITS_SUFFIXES:
        return "aot"
    if p.suffix.lower() in HDF5_SUFFIXES or p.is_file():
        return "hdf5"
    return "lbt" if str(path).endswith("/") or p.name.startswith("Data_") else "hdf5"


def telemetry_input(path: str | Path) -> Path:
    """``path`` if it names a readable telemetry file or folder, else InputError."""
    p = Path(path)
    return p if p.is_dir() else input_file(p, "telemetry file")


def open_telemetry(path: str | Path, required: tuple[str, ...] = REQUIRED) -> TelemetryReader:
    """The model of the telemetry at ``path`` in any format (InputError naming what is wrong)."""
    kind = telemetry_format(path)
    if kind == "aot":
        from .aot import read_aot

        return read_aot(path, required)
    if kind == "lbt":
        from .lbt import read_lbt

        return read_lbt(path, required)
    return TelemetryReader(path, required)


def record_of(tm: TelemetryReader) -> tuple[dict[str, np.ndarray], dict]:
    """Every field of the schema an open model holds (arrays, checked) and its attributes, the
    configuration decoded.  The whole record is read into memory."""
    names = [f.name for f in DATASETS if tm.has(f.name)]
    for task in tm.group("aux") or ():
        names += [f"aux/{task}/{key}" for key in tm.group(f"aux/{task}") or ()]
    arrays = {name: tm.read(name) for name in names}
    attrs = {f.name: tm.attribute(f.name) for f in ATTRIBUTES if f.name != "configuration" and tm.has(f.name)}
    if tm.has("configuration"):
        attrs["configuration"] = tm.configuration()
    return arrays, attrs


def read_record(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """``record_of`` the telemetry at ``path`` (any format; only the fields it holds)."""
    with open_telemetry(path, required=()) as tm:
        return record_of(tm)


def write_record(path: str | Path, arrays: dict, attributes: dict, immediate: bool = False) -> None:
    """A whole record in the format of ``path`` (see ``telemetry_format``), atomically; a file
    lands at the command's commit unless ``immediate`` (a folder always lands at once)."""
    attributes = dict(attributes)
    configuration = attributes.pop("configuration", {})
    kind = telemetry_format(path)
    if kind == "aot":
        from .aot import write_aot

        write_aot(path, arrays, attributes, configuration, immediate)
    elif kind == "lbt":
        from .lbt import write_lbt

        write_lbt(path, arrays, attributes, configuration)
    else:
        from .hdf5 import write_telemetry

        write_telemetry(path, arrays, attributes, configuration, immediate)


def check_decimation(tm: TelemetryReader, path, what: str) -> None:
    """InputError when the rows are not consecutive frames (decimated or skipped frames):
    ``what`` (e.g. "MGM's spectra") needs every frame."""
    if not tm.has("frame_counter") or tm.dim("frames") < 2:
        return
    steps = np.unique(np.diff(tm.read("frame_counter")))
    if steps.size != 1 or steps[0] != 1:
        raise InputError(
            f"telemetry file {path}: field frame_counter steps by {', '.join(str(int(s)) for s in steps[:4])} frames "
            f"(decimated or skipped frames): {what} need every frame"
        )


def stored_run_description(path: str | Path) -> dict:
    """The run description stored in telemetry of any format (``run_config.RunConfig.from_dict``
    reads it); InputError when it holds none."""
    with open_telemetry(telemetry_input(path), required=()) as tm:
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
        return record_of(tm)
