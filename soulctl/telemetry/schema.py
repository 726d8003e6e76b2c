"""The one schema of a telemetry file (what `loop run --telemetry` writes; what
``formats.read_telemetry`` and `optimize gains --telemetry` read) and the reader that
holds a file to it.

``TELEMETRY_SCHEMA`` lists every dataset and attribute: what its values are (real numbers,
integers or text), its shape in named dimensions (frames, n_modes, n_slopes, n_actuators,
changes), the dtype `loop run` writes, the unit and the range of every value.  ``RELATIONS``
are the rules between fields, ``CONFIGURATION_SCHEMA`` the members of the configuration
attribute that soulctl reads back.

``TelemetryReader`` opens a file (a regular file, HDF5) and checks, from the metadata alone,
every field present: a dataset where a dataset belongs, real numbers (not text, complex
numbers, booleans or compound types), the rank, and the dimensions shared between fields.
Values are checked as they are read (finite, in range, integers where integers belong), so
that a reader pays in memory and time only for the rows and columns it asks for.  Every
failure is an InputError that names the field and what is accepted.

A loop that diverged records anything in the frame it diverged at (attribute diverged_at):
the values of per-frame records are checked before that frame.  Links to other files,
external raw storage and virtual datasets are refused: a telemetry file is read from its own
bytes only.
"""

from __future__ import annotations

import io
import json
import math
from contextlib import contextmanager
from dataclasses import dataclass

import h5py
import numpy as np

from ..control.structure import StructuralResonance
from ..errors import InputError
from ..files import input_file
from ..observation import Observation
from ..optics.pupil import LBT_DIAMETER_M, LBT_OBSTRUCTION
from ..ranges import (
    DELAY_FRAMES,
    DIVERGED_AT,
    FORGETTING,
    FRAME_INDEX,
    FRAME_TIME_S,
    LOOP_GAIN,
    MODAL_NM,
    OVERSAMPLING,
    RECORD_MODES,
    RECORD_RATE_HZ,
    RMS_NM,
    SCHEMA_VERSION,
    SENSITIVITY,
    TELEMETRY_EVERY,
    TELESCOPE_M,
    WFS_FIELD_OF_VIEW_ARCSEC,
    Range,
    number_text,
)

# Ranges of recorded values (not options a user types; candidates for soulctl.ranges).

REAL, INTEGER, TEXT = "real numbers", "integers", "text"
# What a record says of its loop (attributes sensor and corrector): the optical-gain model and
# the structural resonance follow from them (``telemetry.loop_model``).
SENSORS = ("pyramid", "shack-hartmann", "quad-cell", "unknown")
CORRECTORS = ("lbt-adaptive-secondary", "deformable-mirror", "tip-tilt-mirror", "unknown")
# LBT's pyramid on its adaptive secondary: what soulctl simulates and LBT's folders record
LBT_SYSTEM = {
    "sensor": "pyramid",
    "corrector": "lbt-adaptive-secondary",
    "telescope": "LBT",
    "telescope_diameter_m": LBT_DIAMETER_M,
    "telescope_obstruction_m": LBT_DIAMETER_M * LBT_OBSTRUCTION,
}


@dataclass(frozen=True)
class Field:
    """One dataset or attribute: its values (REAL, INTEGER or TEXT), its shape in named
    dimensions (() a scalar), the dtype `loop run` writes, the range of every value (None:
    any finite number) and whether NaN and infinities are allowed (``finite=False``)."""

    name: str
    where: str  # "dataset" or "attribute"
    values: str
    shape: tuple[str, ...] = ()
    stored: str = "float64"
    range: Range | None = None
    finite: bool = True
    doc: str = ""

    @property
    def per_frame(self) -> bool:
        return self.shape[:1] == ("frames",)

    def shape_text(self) -> str:
        return "(" + ", ".join(self.shape) + ("," if len(self.shape) == 1 else "") + ")"

    def accepted(self) -> str:
        """What the field holds, as error messages say it."""
        what = f"{self.values} ({self.stored})" if self.values != TEXT else "text"
        return what + (f" in {self.range.text()}" if self.range is not None else "")


def _dataset(name, values, shape, stored, range_=None, doc="", finite=True) -> Field:
    return Field(name, "dataset", values, shape, stored, range_, finite, doc)


def _attribute(name, values, stored, range_=None, doc="") -> Field:
    return Field(name, "attribute", values, (), stored, range_, True, doc)


FRAMES_MODES = ("frames", "n_modes")
DATASETS = (
    _dataset("slopes", REAL, ("frames", "n_slopes"), "float32", None, "slopes s(k) from the slope computer (times k)"),
    _dataset("measured_modes", REAL, FRAMES_MODES, "float32", MODAL_NM, "R s(k)"),
    _dataset("commands", REAL, ("frames", "n_actuators"), "float32", MODAL_NM, "c(k) = Sigma zeta(k)"),
    _dataset("command_modes", REAL, FRAMES_MODES, "float32", MODAL_NM, "M^-1 c(k)"),
    _dataset("mirror_modes", REAL, FRAMES_MODES, "float32", MODAL_NM, "the mirror during frame k (delayed)"),
    _dataset("residual_modes", REAL, FRAMES_MODES, "float32", MODAL_NM, "the simulation's true residual"),
    _dataset("disturbance_modes", REAL, FRAMES_MODES, "float32", MODAL_NM, "the simulation's true disturbance"),
    _dataset("residual_rms_nm", REAL, ("frames",), "float64", RMS_NM),
    _dataset("frame_counter", INTEGER, ("frames",), "int64", FRAME_INDEX, "the loop's frame number k of each row"),
    _dataset("frame_time_s", REAL, ("frames",), "float64", FRAME_TIME_S, "k / frame rate"),
    _dataset("sensitivity", REAL, ("frames",), "float64", SENSITIVITY, "slope sensitivity k during frame k"),
    _dataset("flux", REAL, ("frames",), "float64", None, "detected electrons in frame k (read noise included)"),
    _dataset("gains", REAL, ("n_modes",), "float64", LOOP_GAIN, "per-mode gains at the end"),
    _dataset("reconstructor", REAL, ("n_modes", "n_slopes"), "float32", None, "R: the modes (nm) of the slopes"),
    _dataset("modes_to_commands", REAL, ("n_actuators", "n_modes"), "float32", None, "M: the actuator commands of each mode"),
    _dataset("controller_num", REAL, ("n_modes", "num_terms"), "float64", None, "the time filter of each mode, numerator (z^-1 powers)"),
    _dataset("controller_den", REAL, ("n_modes", "den_terms"), "float64", None, "the time filter of each mode, denominator (z^-1 powers)"),
    _dataset("gain_history/frames", INTEGER, ("changes",), "int64", FRAME_INDEX, "first frame of each gain vector"),
    _dataset("gain_history/gains", REAL, ("changes", "n_modes"), "float64", LOOP_GAIN, "the gain vectors in force from those frames"),
)
# /aux/<task>/<field>: the auxiliary loops' records, rows = updates; NaN marks "no estimate".
AUX_RECORD = _dataset(
    "aux/<task>/<field>",
    REAL,
    ("updates",),
    "float64",
    None,
    "auxiliary loops' records (e.g. /aux/ogtl/sensitivity, /aux/mgm/gains), (updates, ...)",
    finite=False,
)
AUX_FRAME = _dataset("aux/<task>/frame", INTEGER, ("updates",), "int64", FRAME_INDEX, "the first frame after each update")
ATTRIBUTES = (
    _attribute("rate_hz", REAL, "float64", RECORD_RATE_HZ),
    _attribute("delay_frames", REAL, "float64", DELAY_FRAMES),
    _attribute("n_modes", INTEGER, "int64", RECORD_MODES, "= n_modes"),
    _attribute("sensor", TEXT, "str", None, "the wavefront sensor: " + ", ".join(SENSORS)),
    _attribute("corrector", TEXT, "str", None, "what the loop commands: " + ", ".join(CORRECTORS)),
    _attribute("telescope", TEXT, "str", None, "the telescope's name"),
    _attribute("telescope_diameter_m", REAL, "float64", TELESCOPE_M, "its pupil's diameter (the mas of Tip/Tilt)"),
    _attribute("telescope_obstruction_m", REAL, "float64", TELESCOPE_M, "its central obstruction's diameter"),
    _attribute("soulctl_version", TEXT, "str"),
    _attribute("schema_version", INTEGER, "int64", SCHEMA_VERSION, "the layout's version (absent: 1)"),
    _attribute("status", TEXT, "str", None, "complete, partial (see partial_reason) or writing (the writer never closed it)"),
    _attribute("partial_reason", TEXT, "str", None, "why a partial file stopped: interrupted, diverged, an error"),
    _attribute("telemetry_every", INTEGER, "int64", TELEMETRY_EVERY, "one frame in N recorded (frame_counter holds which)"),
    _attribute("diverged_at", INTEGER, "int64", DIVERGED_AT, "the frame the loop diverged at, -1 if it did not"),
    _attribute("configuration", TEXT, "str", None, "JSON object: observation, atmosphere, gains, seed, ..."),
    _attribute("run_description", TEXT, "str", None, "TOML: the resolved run description (soulctl.run_config), re-runnable"),
)
# The unit of every per-frame and gain dataset (stored as its "unit" attribute).
UNITS = {
    "slopes": "normalised slope x k",
    "measured_modes": "nm",
    "commands": "nm",
    "command_modes": "nm",
    "mirror_modes": "nm",
    "residual_modes": "nm",
    "disturbance_modes": "nm",
    "residual_rms_nm": "nm",
    "frame_counter": "frame",
    "frame_time_s": "s",
    "sensitivity": "1",
    "flux": "electron",
    "gains": "1",
    "reconstructor": "nm per slope unit",
    "modes_to_commands": "nm per nm",
    "controller_num": "1",
    "controller_den": "1",
    "gain_history/frames": "frame",
    "gain_history/gains": "1",
}
PER_FRAME = tuple(f.name for f in DATASETS if f.per_frame and f.name not in ("frame_counter", "frame_time_s"))
# `loop run --telemetry-fields` default: the modal records, k and flux (slopes and actuator
# commands on request: at 40x40 they are ~80 % of a frame's bytes).
DEFAULT_FIELDS = tuple(n for n in PER_FRAME if n not in ("slopes", "commands"))
TELEMETRY_SCHEMA: dict[str, Field] = {f.name: f for f in (*DATASETS, AUX_RECORD, AUX_FRAME, *ATTRIBUTES)}
DIMENSION_LABELS = {
    "frames": "frames",
    "n_modes": "modes",
    "n_slopes": "slopes",
    "n_actuators": "actuators",
    "changes": "entries",
    "num_terms": "numerator terms",
    "den_terms": "denominator terms",
    "updates": "updates",
}
RELATIONS = (
    "every dimension name has one size across the fields that use it",
    "gain_history holds both frames and gains, or neither",
    "gain_history/frames increases strictly and is at most frames (gains set after the last frame)",
    "n_modes (attribute) is the n_modes of the datasets",
    "diverged_at is -1 or at most frames",
    "aux/<task>/*: one row per update (the task's 'updates'); aux/<task>/frame at most frames",
)
# Members of the configuration attribute that soulctl reads back (others are informational).
CONFIGURATION_SCHEMA = {
    "observation": "an observation as `soulctl configure` writes it (JSON object); required unless --config or --mag",
    "oversampling": OVERSAMPLING,
    "field_of_view_arcsec": WFS_FIELD_OF_VIEW_ARCSEC,  # absent: 0, written before SOUL's field was the default
    "gains.forgetting": FORGETTING,
    "structure": "null or {frequency_hz, damping, coupling} (soulctl.control.structure)",
}
REQUIRED = ("measured_modes", "command_modes", "gains", "rate_hz", "delay_frames")  # offline MGM's needs
FLOAT32 = tuple(f.name for f in DATASETS if f.stored == "float32")


@dataclass(frozen=True)
class Note:
    """What a format's reader assumed, derived or could not find (``field``: the model's field
    it concerns, "" for the record as a whole), as `telemetry inspect` prints it."""

    field: str
    text: str


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split()) or type(e).__name__


def describe(value) -> str:
    """A value as error messages show it: numbers with number_text, the rest briefly."""
    if isinstance(value, (bytes, np.bytes_)):
        value = bytes(value).decode("utf-8", "replace")
    if isinstance(value, str):
        return repr(value if len(value) <= 40 else value[:40] + "...")
    if isinstance(value, bool):
        return repr(value)
    if isinstance(value, int) and abs(value) >= 10**20:
        return f"an integer of {len(str(abs(value)))} digits"
    if isinstance(value, (int, float)):
        return number_text(value)
    if isinstance(value, complex):
        return f"the complex number {value}"
    if isinstance(value, (list, tuple, dict)):
        return f"a JSON {'object' if isinstance(value, dict) else 'array'}"
    if value is None:
        return "null"
    return type(value).__name__


FINITE = Range(-math.inf, math.inf)  # any finite number (an int of any size; not a bool)


def check_number(range_: Range, value, name: str):
    """``range_.check`` for any value (text, arrays and huge integers included): the value, or
    an InputError naming ``name``, the range and the value."""
    if not range_.contains(value):  # False for text, arrays, bools, NaN and infinities
        kind = "an integer" if range_.integer else "a number"
        raise InputError(f"{name} must be {kind} in {range_.text()}, got {describe(value)}")
    return range_.check(value, name)


def _values_kind(dtype: np.dtype) -> str:
    """REAL or INTEGER for numeric dtypes, else what the values are, in words."""
    kind = dtype.kind
    if kind in "iu":
        return INTEGER
    if kind == "f":
        return REAL
    return {
        "c": "complex numbers",
        "b": "booleans",
        "S": "text",
        "U": "text",
        "O": "text or object references",
        "V": "compound or opaque values",
    }.get(kind, f"values of type {dtype}")


COMPRESSION = {"compression": "gzip", "compression_opts": 1, "shuffle": True}


def stored(name: str, data) -> np.ndarray:
    """A field's values in the dtype files store it in: int64 for integers (and booleans),
    float32 or float64 for real numbers as the schema says; other kinds as they are (the
    reader refuses them, naming the field)."""
    data = np.asarray(data)
    if data.dtype.kind in "iub":
        return data.astype(np.int64)
    if data.dtype.kind == "f":
        return data.astype(np.float32 if name in FLOAT32 else np.float64)
    return data


def store(f: h5py.File, arrays: dict, attributes: dict) -> None:
    """Fields of the schema into an open HDF5 file, each in its stored dtype with its unit."""
    for name, data in arrays.items():
        data = stored(name, data)
        f.create_dataset(name, data=data, **(COMPRESSION | {"chunks": True} if data.ndim == 2 and data.size > 4096 else {}))
        if name in UNITS:
            f[name].attrs["unit"] = UNITS[name]
    for key, value in attributes.items():
        f.attrs[key] = json.dumps(value) if key == "configuration" and isinstance(value, dict) else value


def _attribute_value(raw):
    """An attribute as a Python scalar (int, float, str) when it is one value, else as is."""
    if isinstance(raw, (str, bytes)):
        return raw
    if isinstance(raw, h5py.Empty):
        return None
    a = np.asarray(raw)
    if a.size != 1:
        return a
    v = a.reshape(()).item()
    return v


class TelemetryReader:
    """An open telemetry file whose layout matches the schema (see the module); use as a
    context manager.  ``required``: the fields the reader cannot do without."""

    def __init__(self, path, required: tuple[str, ...] = REQUIRED, file: h5py.File | None = None, notes: tuple[Note, ...] = ()):
        self.path = path
        self.notes = tuple(notes)  # what the format's reader assumed or could not find (``Note``)
        self.dims: dict[str, tuple[int, str]] = {}  # dimension -> (size, the field that set it)
        self.file = file if file is not None else self._open(path)
        try:
            with self._reading("its layout"):
                self._check_layout(required)
        except BaseException:
            self.file.close()
            raise

    @staticmethod
    def _open(path) -> h5py.File:
        p = input_file(path, "telemetry file")
        try:
            hdf5 = h5py.is_hdf5(p)
        except OSError as e:
            raise InputError(f"cannot read telemetry file {path}: {_one_line(e)}") from None
        if not hdf5:
            raise InputError(f"telemetry file {path} is not an HDF5 file, an AOT FITS file (.fits) or an LBT tracking-number folder")
        try:
            return h5py.File(p, "r")
        except OSError as e:
            raise InputError(f"cannot read telemetry file {path}: {_one_line(e)}") from None

    @classmethod
    def from_arrays(
        cls,
        path,
        arrays: dict,
        attributes: dict,
        required: tuple[str, ...] = REQUIRED,
        notes: tuple[Note, ...] = (),
        slopes_unit: str = UNITS["slopes"],
    ) -> TelemetryReader:
        """The model of a record read from another format (AOT FITS, an LBT folder): the same
        fields, held in an in-memory HDF5 file and checked alike; ``notes``: what its reader
        assumed or found missing; ``slopes_unit``: the unit of the record's slopes (every other
        field's is the schema's)."""
        f = h5py.File(io.BytesIO(), "w")
        store(f, arrays, attributes)
        if "slopes" in arrays:
            f["slopes"].attrs["unit"] = slopes_unit
        return cls(path, required, file=f, notes=notes)

    def lacks(self, names, use: str = "") -> InputError:
        """The error for fields the record lacks, with what its reader found of them and what
        ``use`` needs them for."""
        why = [n.text for n in self.notes if n.field in names]
        text = f"telemetry file {self.path} lacks {', '.join(names)}" + (f" ({'; '.join(why)})" if why else "")
        if names == ["delay_frames"] and use:
            text += f", which {use} needs: give --delay-frames (telemetry identify estimates it)"
        return InputError(text)

    def __enter__(self) -> TelemetryReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self.file.close()

    def _error(self, text: str) -> InputError:
        return InputError(f"telemetry file {self.path}: {text}")

    @contextmanager
    def _reading(self, what: str):
        """h5py's errors (a damaged file, an unsupported type) as InputErrors."""
        try:
            yield
        except InputError:
            raise
        except (OSError, RuntimeError, KeyError, TypeError, ValueError, OverflowError, IndexError) as e:
            raise self._error(f"cannot read {what} ({_one_line(e)})") from None

    # ---------------------------------------------------------------------- structure

    def node(self, name: str):
        """The group or dataset at ``name`` (None if absent); InputError for a dataset on the
        way, a link to another file, external raw storage or a virtual dataset."""
        with self._reading(name):
            return self._node(name)

    def _node(self, name: str):
        obj = self.file
        parts = name.split("/")
        for i, part in enumerate(parts):
            where = "/".join(parts[: i + 1])
            if not isinstance(obj, h5py.Group):
                raise self._error(f"{'/'.join(parts[:i])} is a dataset, expected a group (holding {name})")
            link = obj.get(part, getlink=True)
            if link is None:
                return None
            if isinstance(link, h5py.ExternalLink):
                raise self._error(f"{where} is a link to another file ({link.filename}): soulctl reads a telemetry file's own data only")
            obj = obj.get(part)
            if obj is None:  # a dangling soft link
                return None
        if isinstance(obj, h5py.Dataset):
            if obj.is_virtual or obj.external:
                raise self._error(f"field {name} keeps its data in other files: soulctl reads a telemetry file's own data only")
        elif not isinstance(obj, h5py.Group):
            raise self._error(f"{name} is a {type(obj).__name__}, expected a dataset or a group")
        return obj

    def dataset(self, name: str) -> h5py.Dataset | None:
        obj = self.node(name)
        if obj is not None and not isinstance(obj, h5py.Dataset):
            raise self._error(f"field {name} is a group, expected a dataset of {TELEMETRY_SCHEMA.get(name, AUX_RECORD).accepted()}")
        return obj

    def group(self, name: str) -> h5py.Group | None:
        obj = self.node(name)
        if obj is not None and not isinstance(obj, h5py.Group):
            raise self._error(f"{name} is a dataset, expected a group")
        return obj

    def has(self, name: str) -> bool:
        return self.node(name) is not None if TELEMETRY_SCHEMA.get(name, AUX_RECORD).where == "dataset" else name in self.file.attrs

    def unit(self, name: str) -> str:
        """The unit of dataset ``name``: its "unit" attribute, else the schema's."""
        ds = self.dataset(name)
        unit = ds.attrs.get("unit") if ds is not None else None
        return unit if isinstance(unit, str) else UNITS.get(name, "")

    def dim(self, name: str) -> int:
        return self.dims[name][0]

    def _bind(self, dim: str, size: int, name: str) -> None:
        if dim in self.dims and self.dims[dim][0] != size:
            bound, other = self.dims[dim]
            label = DIMENSION_LABELS.get(dim, dim)
            raise self._error(f"field {name} has {size} {label}, {other} has {bound}: the fields must agree")
        self.dims.setdefault(dim, (size, name))

    def _check_dataset(self, field: Field, name: str, shape: tuple[str, ...]) -> h5py.Dataset | None:
        ds = self.dataset(name)
        if ds is None:
            return None
        kind = _values_kind(ds.dtype)
        if kind not in (REAL, INTEGER):
            raise self._error(f"field {name} holds {kind}, expected {field.accepted()}")
        if ds.shape is None:
            raise self._error(f"field {name} is empty (no dataspace), expected {field.accepted()}")
        if field is AUX_RECORD or field is AUX_FRAME:
            if ds.ndim < 1 or (field is AUX_FRAME and ds.ndim != 1):
                raise self._error(f"field {name} has shape {ds.shape}, expected (updates{', ...' if field is AUX_RECORD else ','})")
        elif ds.ndim != len(shape):
            raise self._error(f"field {name} has shape {ds.shape}, expected {field.shape_text()}")
        for axis, dim in enumerate(shape):
            self._bind(dim, int(ds.shape[axis]), name)
        return ds

    def _check_layout(self, required: tuple[str, ...]) -> None:
        version = _attribute_value(self.file.attrs.get("schema_version", 1))
        if isinstance(version, (int, np.integer)) and not isinstance(version, bool) and version > SCHEMA_VERSION.hi:
            raise self._error(
                f"schema version {version} is newer than this soulctl reads ({SCHEMA_VERSION.text()}): update soulctl to read it"
            )
        missing = [n for n in required if not self.has(n)]
        if missing:
            raise self.lacks(missing)
        # the required fields first: a disagreement names the field that is off
        for field in sorted(DATASETS, key=lambda f: f.name not in required):
            self._check_dataset(field, field.name, field.shape)
        aux = self.group("aux")
        for task in aux or ():
            records = self.group(f"aux/{task}")
            for key in records or ():
                field = AUX_FRAME if key == "frame" else AUX_RECORD
                self._check_dataset(field, f"aux/{task}/{key}", (f"updates of aux/{task}",))
        for field in ATTRIBUTES:
            if field.name in self.file.attrs:
                self.attribute(field.name)
        self._configuration = self._decode_configuration()
        if "n_modes" in self.file.attrs and "n_modes" in self.dims and self.attribute("n_modes") != self.dim("n_modes"):
            raise self._error(
                f"attribute n_modes is {self.attribute('n_modes')}, {self.dims['n_modes'][1]} has {self.dim('n_modes')} modes"
            )
        if self.has("gain_history/frames") != self.has("gain_history/gains"):
            raise self._error("gain_history needs both frames and gains (the gain vectors and the frames they apply from)")
        changes = self.dims.get("changes", (0,))[0]
        if changes > self.dims.get("frames", (0,))[0] + 1:
            raise self._error(
                f"field gain_history/frames has {changes} entries for {self.dims.get('frames', (0,))[0]} frames: at most one per frame"
            )

    # ------------------------------------------------------------------------- values

    def attribute(self, name: str, default=InputError):
        """A checked attribute: a number in its range or text (``default`` when absent; an
        InputError naming it when absent without a default)."""
        field = TELEMETRY_SCHEMA[name]
        if name not in self.file.attrs:
            if default is InputError:
                raise self.lacks([name])
            return default
        with self._reading(f"attribute {name}"):
            raw = _attribute_value(self.file.attrs[name])
        label = f"telemetry file {self.path}: attribute {name}"
        if field.values == TEXT:
            if isinstance(raw, (bytes, np.bytes_)):
                try:
                    return bytes(raw).decode("utf-8")
                except UnicodeDecodeError:
                    raise InputError(f"{label} is not UTF-8 text") from None
            if not isinstance(raw, str):
                shown = f"an array of shape {raw.shape}" if isinstance(raw, np.ndarray) else describe(raw)
                raise InputError(f"{label} must be text, got {shown}")
            return raw
        assert field.range is not None  # every numeric attribute of the schema has its range
        if isinstance(raw, np.ndarray):
            kind = "an integer" if field.range.integer else "a number"
            raise InputError(f"{label} must be {kind} in {field.range.text()}, got an array of shape {raw.shape}")
        value = check_number(field.range, raw, label)
        if name == "diverged_at" and "frames" in self.dims and value > self.dim("frames"):
            raise InputError(f"{label} is {value}, beyond the file's {self.dim('frames')} frames")
        return value

    def configuration(self) -> dict:
        """The configuration attribute as a dict ({} when absent)."""
        return self._configuration

    def _decode_configuration(self) -> dict:
        text = self.attribute("configuration", None)
        if text is None:
            return {}
        try:
            conf = json.loads(text)
        except (ValueError, RecursionError):
            raise self._error("attribute configuration is not JSON") from None
        if not isinstance(conf, dict):
            raise self._error(f"attribute configuration must be a JSON object, got {describe(conf)}")
        return conf

    def read(self, name: str, rows: slice = slice(None), columns: slice | None = None) -> np.ndarray:
        """The checked values of dataset ``name`` (rows, and columns of a 2-D one): float32 or
        float64 as stored (int64 for integer fields), finite and in the field's range, or an
        InputError."""
        field = TELEMETRY_SCHEMA.get(name) or (AUX_FRAME if name.endswith("/frame") else AUX_RECORD)
        ds = self.dataset(name)
        if ds is None:
            raise self.lacks([name])
        with self._reading(f"field {name}"):
            data = ds[rows] if columns is None else ds[rows, columns]
        data = np.asarray(data)
        checked = data
        if field.per_frame and self._diverged() >= 0:  # rows from the divergence on hold anything
            head = range(ds.shape[0])[rows][:1]
            first = head[0] if len(head) else 0
            checked = data[: max(0, self._diverged() - first)]
        values = self._checked(field, name, data, checked)
        if field is TELEMETRY_SCHEMA["gain_history/frames"] or field is AUX_FRAME:
            frames = self.dims.get("frames", (None,))[0]
            if field is not AUX_FRAME and np.any(np.diff(values) <= 0):
                raise self._error(f"field {name} must increase strictly (one gain vector per first frame)")
            if frames is not None and values.size and values.max() > frames:
                raise self._error(f"field {name} holds frame {values.max()}, beyond the file's {frames} frames")
        return values

    def _diverged(self) -> int:
        return self.attribute("diverged_at", -1)

    def _checked(self, field: Field, name: str, data: np.ndarray, checked: np.ndarray) -> np.ndarray:
        if checked.dtype.kind == "f" and field.finite:
            bad = int(np.count_nonzero(~np.isfinite(checked)))
            if bad:
                raise self._error(f"field {name} has {bad} NaN or infinite values")
        r = field.range
        if r is not None and checked.size:
            with np.errstate(invalid="ignore"):
                ok = (checked > r.lo if r.lo_open else checked >= r.lo) & (checked < r.hi if r.hi_open else checked <= r.hi)
                if r.integer and checked.dtype.kind == "f":
                    ok &= checked == np.floor(checked)
            if not field.finite:
                ok |= ~np.isfinite(checked)
            if not ok.all():
                value = checked[~ok].flat[0].item()
                raise self._error(f"field {name} must hold {field.values} in {r.text()}, got {describe(value)}")
        if field.values == INTEGER:
            if data.dtype.kind == "f" and not np.all(np.isfinite(data) & (np.abs(data) < 2**63)):
                raise self._error(f"field {name} must hold integers, got {describe(data[~np.isfinite(data)].flat[0].item())}")
            return data.astype(np.int64)
        return data if data.dtype in (np.float32, np.float64) else data.astype(np.float64)


def nested(conf, *keys, number: bool = False):
    """conf[k1][k2]... when every level is a JSON object and the last is there (and, with
    ``number``, a finite number), else None: what a report or a writer takes when present."""
    for key in keys:
        if not isinstance(conf, dict) or key not in conf:
            return None
        conf = conf[key]
    if number and not FINITE.contains(conf):
        return None
    return conf


def check_slope_pairs(arrays: dict, what: str) -> None:
    """InputError unless the slopes (when present) come in x, y pairs, as a format of x and y
    slopes (AOT's 2 dimensions, LBT's interleaved order) needs."""
    if "slopes" in arrays and np.shape(arrays["slopes"])[1] % 2:
        raise InputError(f"field slopes has {np.shape(arrays['slopes'])[1]} columns: {what} needs x, y pairs")


def configuration_member(conf: dict, name: str, default, path):
    """A number of the configuration (``gains.forgetting``: a member of a member), checked
    against CONFIGURATION_SCHEMA; ``default`` when absent."""
    *outer, key = name.split(".")
    section = conf
    for part in outer:
        section = section.get(part, {})
        if not isinstance(section, dict):
            raise InputError(f"telemetry file {path}: attribute configuration.{part} must be a JSON object, got {describe(section)}")
    if key not in section:
        return default
    accepted = CONFIGURATION_SCHEMA[name]
    assert isinstance(accepted, Range)  # configuration_member reads the numeric members only
    return check_number(accepted, section[key], f"telemetry file {path}: attribute configuration.{name}")


def configuration_observation(conf: dict, path) -> Observation:
    """The configuration's observation (InputError naming what is wrong)."""
    if "observation" not in conf:
        raise InputError(f"telemetry file {path} lacks the configuration attribute (observation); give --config or --mag")
    try:
        return Observation.from_dict(conf["observation"])
    except (TypeError, KeyError, AttributeError, ValueError, OverflowError, RecursionError) as e:
        raise InputError(f"telemetry file {path}: attribute configuration.observation is not an observation ({_one_line(e)})") from None


def configuration_structure(conf: dict, path) -> StructuralResonance | None:
    """The configuration's structural resonance (None when absent or null)."""
    d = conf.get("structure")
    if d is None:
        return None
    what = f"telemetry file {path}: attribute configuration.structure"
    if not isinstance(d, dict):
        raise InputError(f"{what} must be null or a JSON object {{frequency_hz, damping, coupling}}, got {describe(d)}")
    for key, value in d.items():
        if not FINITE.contains(value):
            raise InputError(f"{what}.{key} must be a finite number, got {describe(value)}")
    try:
        return StructuralResonance(**d)
    except (TypeError, ValueError) as e:
        raise InputError(f"{what} is not a resonance ({_one_line(e)})") from None
