"""Writing files atomically: a temporary file in the target's folder, then a rename, so that a
reader never sees a half-written file and a failed write leaves nothing behind."""

from __future__ import annotations

import os
import tempfile
import tomllib
from collections.abc import Callable
from pathlib import Path

from .errors import InputError


def atomic_write(path: str | Path, write: Callable[[str], None]) -> None:
    """Call ``write(tmp_path)`` to produce the file, then rename it onto ``path`` (mode 0644)."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=".soulctl-", suffix=".tmp" + path.suffix, dir=path.parent or ".")
    try:
        os.fchmod(fd, 0o644)  # mkstemp makes 0600; results are for everyone to read
        os.close(fd)
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    def write(tmp: str) -> None:
        with open(tmp, "w") as f:
            f.write(text)

    atomic_write(path, write)


def check_output_path(path: Path, option: str) -> None:
    """An output path must name a file in an existing folder (InputError otherwise)."""
    if path.is_dir():
        raise InputError(f"{option} must be a file path, got the directory {path}")
    if not path.parent.exists():
        raise InputError(f"{option}: the folder {path.parent} does not exist")


def read_toml(path: str | Path, what: str) -> dict:
    """A TOML file as a dict; a missing, unreadable or invalid file is an InputError naming
    ``what`` (e.g. "configuration file") and the path."""
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise InputError(f"{what} not found: {path}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{what} {path} is not valid TOML: {e}") from None
    except OSError as e:
        raise InputError(f"cannot read {what} {path}: {e.strerror or e}") from None
