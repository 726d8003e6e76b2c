"""An on-disk cache of computed arrays (modal bases, interaction matrices), keyed by the
parameters that determine them.

A key is the SHA-256 of the canonical JSON of those parameters plus ``MODEL_VERSION`` (bumped
whenever a model change alters cached results).  Entries are ``.npz`` files written
atomically (temporary file, then rename), so an interrupted run leaves either the whole entry
or nothing; an unreadable entry counts as a miss and is recomputed.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..files import atomic_write

MODEL_VERSION = 2  # 2: the pyramid sums its modulation points per thread (float32 rounding changed)


def cache_key(kind: str, params: dict) -> str:
    text = json.dumps({"kind": kind, "model_version": MODEL_VERSION, **params}, sort_keys=True, default=str)
    return f"{kind}-{hashlib.sha256(text.encode()).hexdigest()[:20]}"


@dataclass(frozen=True)
class ArrayCache:
    """``directory=None`` disables the cache (every load misses, nothing is stored)."""

    directory: Path | None

    def path(self, key: str) -> Path | None:
        return None if self.directory is None else Path(self.directory) / f"{key}.npz"

    def load(self, key: str) -> dict[str, np.ndarray] | None:
        path = self.path(key)
        if path is None or not path.exists():
            return None
        try:
            with np.load(path, allow_pickle=False) as data:
                return {name: data[name] for name in data.files}
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            return None

    def store(self, key: str, arrays: dict[str, np.ndarray]) -> None:
        path = self.path(key)
        if path is None:
            return
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            atomic_write(path, lambda tmp: np.savez(tmp, **arrays))
        except OSError:  # a cache that cannot be written (e.g. a sweep worker on another host) is no cache
            return
