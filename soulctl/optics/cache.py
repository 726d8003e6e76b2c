"""An on-disk cache of computed arrays (modal bases, interaction matrices, optical-gain tables),
keyed by the parameters that determine them.

A key is the SHA-256 of the canonical JSON of those parameters plus ``MODEL_VERSION`` (bumped
whenever a model change alters cached results).  Entries are ``.npz`` files written
atomically (temporary file, then rename) and at once, not staged with the command's outputs:
an interrupted run leaves either the whole entry or nothing, and a command that fails later
keeps what it computed.

Each entry carries ``CHECKSUM``, the SHA-256 of its arrays (``checksum``: each array's name,
dtype, shape and bytes, in name order).  ``load`` returns an entry only when it is a regular
file holding exactly the arrays its caller expects (``EntrySpec``: names and shapes), real,
finite and within ``MAX_ENTRY_BYTES``, with a matching checksum.  Anything else is a miss - a
damaged or truncated file, an entry written before checksums, a foreign ``.npz``, arrays
zeroed, scaled, dropped or reshaped - and the caller recomputes; ``store`` then overwrites it.
"""

from __future__ import annotations

import hashlib
import json
import math
import zipfile
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import atomic_write, input_file

MODEL_VERSION = 3  # 2: the pyramid sums its modulation points per thread (float32 rounding changed); 3: KL signs fixed
CHECKSUM = "__sha256__"  # the array holding the checksum of the others
MAX_ENTRY_BYTES = 2**30  # the largest entry loaded (the 671-mode basis is 7 MB)
_HEADER_READERS = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}


def cache_key(kind: str, params: dict) -> str:
    text = json.dumps({"kind": kind, "model_version": MODEL_VERSION, **params}, sort_keys=True, default=str)
    return f"{kind}-{hashlib.sha256(text.encode()).hexdigest()[:20]}"


def checksum(arrays: Mapping[str, np.ndarray]) -> str:
    """SHA-256 (hex) over each array's name, dtype, shape and bytes (C order), in name order."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.asarray(arrays[name])
        h.update(f"{name}\0{a.dtype.str}\0{a.shape}\0".encode())
        h.update((a if a.flags.c_contiguous else a.copy(order="C")).data)
    return h.hexdigest()


@dataclass(frozen=True)
class EntrySpec:
    """The arrays a caller expects in an entry: name -> shape, each dimension an int (exactly
    that size) or a name (one size wherever that name appears, within ``sizes[name]``, an
    inclusive (lo, hi), when given)."""

    shapes: Mapping[str, tuple[int | str, ...]]
    sizes: Mapping[str, tuple[int, int]] = field(default_factory=dict)

    def matches(self, shapes: Mapping[str, tuple[int, ...]]) -> bool:
        if set(shapes) != set(self.shapes):
            return False
        bound: dict[str, int] = {}
        for name, expected in self.shapes.items():
            shape = shapes[name]
            if len(shape) != len(expected):
                return False
            for size, dim in zip(shape, expected):
                if isinstance(dim, str):
                    lo, hi = self.sizes.get(dim, (0, math.inf))
                    if bound.setdefault(dim, size) != size or not lo <= size <= hi:
                        return False
                elif size != dim:
                    return False
        return True


def _headers(z: zipfile.ZipFile) -> dict[str, tuple[tuple[int, ...], np.dtype]] | None:
    """name -> (shape, dtype) of each array of the archive, from the .npy headers (no data
    read); None if a member is not an array."""
    out = {}
    for info in z.infolist():
        if not info.filename.endswith(".npy"):
            return None
        with z.open(info) as fh:
            reader = _HEADER_READERS.get(np.lib.format.read_magic(fh))
            if reader is None:
                return None
            shape, _, dtype = reader(fh)
        out[info.filename[:-4]] = (tuple(shape), dtype)
    return out


@dataclass(frozen=True)
class ArrayCache:
    """``directory=None`` disables the cache (every load misses, nothing is stored)."""

    directory: str | Path | None

    def path(self, key: str) -> Path | None:
        return None if self.directory is None else Path(self.directory) / f"{key}.npz"

    def load(self, key: str, spec: EntrySpec) -> dict[str, np.ndarray] | None:
        """The arrays of entry ``key`` if it is a valid entry as ``spec`` describes it (see the
        module), else None (a miss)."""
        path = self.path(key)
        if path is None or not path.exists():
            return None
        try:
            input_file(path, "cache entry")  # a directory, FIFO or device is no entry
            with zipfile.ZipFile(path) as z:
                headers = _headers(z)
                if headers is None or CHECKSUM not in headers:
                    return None  # not a soulctl entry, or one from before checksums
                shape, dtype = headers.pop(CHECKSUM)
                if shape != () or dtype.kind != "U" or not spec.matches({n: s for n, (s, _) in headers.items()}):
                    return None
                if any(d.kind != "f" for _, d in headers.values()):
                    return None
                if sum(math.prod(s) * d.itemsize for s, d in headers.values()) > MAX_ENTRY_BYTES:
                    return None
                arrays = {}
                for name in (*headers, CHECKSUM):
                    with z.open(f"{name}.npy") as fh:
                        arrays[name] = np.lib.format.read_array(fh, allow_pickle=False)
        except (InputError, OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error, NotImplementedError, RuntimeError):
            return None  # unreadable: a miss
        stored = str(arrays.pop(CHECKSUM)[()])
        if not all(np.isfinite(a).all() for a in arrays.values()) or checksum(arrays) != stored:
            return None
        return arrays

    def store(self, key: str, arrays: dict[str, np.ndarray]) -> None:
        """Write entry ``key`` (replacing any) with the checksum of ``arrays``; a cache that
        cannot be written is no cache (e.g. a sweep worker on another host): nothing happens."""
        path = self.path(key)
        if path is None:
            return
        arrays = {name: np.asarray(a) for name, a in arrays.items()}
        payload = {**arrays, CHECKSUM: np.array(checksum(arrays))}
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(path, lambda tmp: np.savez(tmp, **payload), immediate=True)  # type: ignore[arg-type]  # numpy's stub types **kwds as bool
        except (OSError, InputError):  # InputError: something that is not a regular file at the path
            return
