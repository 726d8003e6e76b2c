"""A minimal writer of IDL save files (``.sav``), for test fixtures only: LBT's supervisor
stores the loop's gains as ``g_gain`` and the calibration files' names in the structure
``status`` of ``adsec.sav`` (icprog/MagAO idl/adsec_lib/adsec_scripts/fsm_savestatus.pro:5-21),
and no such file is public.  No Python package writes the format, so this writes the records
scipy.io.readsav reads (scipy/io/_idl.py: VARIABLE records of float arrays and of a structure
of string tags, then END_MARKER), and the tests check that readsav reads them back.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

VARIABLE, END_MARKER = 2, 6
FLOAT, STRING, STRUCT = 4, 7, 8
ARRAY_FLAG, STRUCT_FLAG = 4, 32


def _long(v: int) -> bytes:
    return struct.pack(">l", v)


def _string(text: str) -> bytes:
    """A name: its length, then its bytes padded to 4."""
    raw = text.encode("latin1")
    return _long(len(raw)) + raw + b"\0" * (-len(raw) % 4)


def _string_data(text: str) -> bytes:
    """A string value: its length twice, then its bytes padded to 4."""
    raw = text.encode("latin1")
    return _long(len(raw)) + _long(len(raw)) + raw + b"\0" * (-len(raw) % 4) if raw else _long(0)


def _array_desc(nbytes: int, nelements: int, dims: tuple[int, ...]) -> bytes:
    full = list(dims) + [0] * (8 - len(dims))
    return _long(8) + _long(0) + _long(nbytes) + _long(nelements) + _long(len(dims)) + b"\0" * 8 + _long(8) + b"".join(map(_long, full))


def _float_array(name: str, values: np.ndarray) -> bytes:
    a = np.asarray(values, dtype=">f4")
    desc = _long(FLOAT) + _long(ARRAY_FLAG) + _array_desc(a.nbytes, a.size, tuple(reversed(a.shape)))
    return _string(name) + desc + _long(7) + a.tobytes()


def _string_struct(name: str, tags: dict[str, str]) -> bytes:
    """A scalar structure whose tags are all strings (e.g. status.b0_a)."""
    table = b"".join(_long(0) + _long(STRING) + _long(0) for _ in tags)
    names = b"".join(_string(t.upper()) for t in tags)
    struct_desc = _long(9) + _string("") + _long(0) + _long(len(tags)) + _long(0) + table + names
    desc = _long(STRUCT) + _long(STRUCT_FLAG | ARRAY_FLAG) + _array_desc(0, 1, (1,)) + struct_desc
    return _string(name) + desc + _long(7) + b"".join(_string_data(v) for v in tags.values())


def write_sav(path: Path, arrays: dict[str, np.ndarray] | None = None, structs: dict[str, dict[str, str]] | None = None) -> Path:
    """An uncompressed IDL save file holding float arrays and string structures."""
    bodies = [_float_array(k, v) for k, v in (arrays or {}).items()]
    bodies += [_string_struct(k, v) for k, v in (structs or {}).items()]
    out = bytearray(b"SR\x00\x04")
    for body in bodies:
        start = len(out)
        nextrec = start + 16 + len(body)
        out += _long(VARIABLE) + struct.pack(">I", nextrec) + _long(0) + b"\0" * 4 + body
    out += _long(END_MARKER) + struct.pack(">I", len(out) + 16) + _long(0) + b"\0" * 4
    Path(path).write_bytes(bytes(out))
    return Path(path)
