"""The files soulctl reads and writes, with one set of rules for all of them.

Inputs (configuration, vibration, grid, gain, roots and telemetry files) are read only when
they are regular files (a FIFO would block, a device such as /dev/zero never ends), text files
only up to ``MAX_TEXT_BYTES``; anything else is an InputError naming the file.

Outputs are written atomically: to a temporary file in the target's folder, then renamed onto
the target, so that a reader never sees a half-written file.  An output path must be a new
path or an existing regular file that is writable; a symlink is written through to its target.
Devices, FIFOs, sockets and directories are never replaced, a read-only file is refused and
an existing file keeps its permission bits.  ``check_output_path`` checks all that before any
work (and that the folder can be written and the path is not one of the command's inputs).

Inside ``staged_outputs()`` (every command line runs in one) the renames wait for
``commit()``: a command that fails, or is interrupted, leaves no new or changed output, and
its temporaries are removed.  Files that must land at once (the calibration cache, a sweep's
results rows) use ``immediate=True``.
"""

from __future__ import annotations

import os
import stat
import tempfile
import tomllib
from collections.abc import Callable, Iterable
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

from .errors import InputError

MAX_TEXT_BYTES = 16 * 2**20  # TOML and CSV inputs
NEW_FILE_MODE = 0o644  # results are for everyone to read
_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISSOCK, "a socket"),
)


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def _size_text(n: int) -> str:
    return f"{n / 2**20:.3g} MB" if n < 2**30 else f"{n / 2**30:.3g} GB"


# ----------------------------------------------------------------------------------- inputs


def input_file(path: str | Path, what: str, max_bytes: int | None = None) -> Path:
    """``path`` if it names a readable regular file (of at most ``max_bytes``), else InputError."""
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise InputError(f"{what} not found: {path}") from None
    except OSError as e:
        raise InputError(f"cannot read {what} {path}: {e.strerror or e}") from None
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{what} {path} is {_kind(st.st_mode)}: soulctl reads regular files only")
    if max_bytes is not None and st.st_size > max_bytes:
        raise InputError(f"{what} {path} is {_size_text(st.st_size)}, more than the {_size_text(max_bytes)} accepted")
    return p


def read_input_bytes(path: str | Path, what: str, max_bytes: int = MAX_TEXT_BYTES) -> bytes:
    """The bytes of a regular input file of at most ``max_bytes`` (InputError otherwise)."""
    p = input_file(path, what, max_bytes)
    try:
        with open(p, "rb") as f:
            data = f.read(max_bytes + 1)
    except OSError as e:
        raise InputError(f"cannot read {what} {path}: {e.strerror or e}") from None
    if len(data) > max_bytes:  # grew since the check
        raise InputError(f"{what} {path} is more than the {_size_text(max_bytes)} accepted")
    return data


def read_input_text(path: str | Path, what: str, max_bytes: int = MAX_TEXT_BYTES) -> str:
    """A UTF-8 text input file (a byte-order mark is accepted); InputError if it is not text."""
    data = read_input_bytes(path, what, max_bytes)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InputError(f"{what} {path} is not UTF-8 text") from None


def read_toml(path: str | Path, what: str) -> dict:
    """A TOML file as a dict; a missing, unreadable, oversized or invalid file is an
    InputError naming ``what`` (e.g. "configuration file") and the path."""
    return parse_toml(read_input_text(path, what), path, what)


def parse_toml(text: str, path: str | Path, what: str) -> dict:
    """``text``, read from ``path``, as a dict; invalid TOML is an InputError naming ``what``."""
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{what} {path} is not valid TOML: {e}") from None


# ---------------------------------------------------------------------------------- outputs


def output_target(path: str | Path) -> Path:
    """Where writing ``path`` lands: a symlink's final target, else the path itself."""
    p = Path(path)
    return Path(os.path.realpath(p)) if p.is_symlink() else p


def same_file(a: str | Path, b: str | Path) -> bool:
    """Whether two paths name one file (through links; by name when either does not exist)."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return os.path.realpath(a) == os.path.realpath(b)


def check_output_path(path: str | Path, option: str, inputs: Iterable[tuple[str, str | Path | None]] = ()) -> Path:
    """Check, before any work, that ``path`` can be written as the output of ``option``: not
    one of ``inputs`` ((option, path) pairs), a new path or a writable regular file, in a
    folder that can be written.  Returns the target (a symlink's target)."""
    for in_option, in_path in inputs:
        if in_path is not None and same_file(path, in_path):
            raise InputError(f"{option} {path} is also the input {in_option}: writing it would destroy the input; choose another path")
    target = output_target(path)
    try:
        st = os.stat(target)
    except FileNotFoundError:
        st = None
    except OSError as e:  # e.g. a path under a file (ENOTDIR)
        raise InputError(f"{option}: cannot write {path}: {e.strerror or e}") from None
    if st is not None:
        if not stat.S_ISREG(st.st_mode):
            raise InputError(f"{option} {path} is {_kind(st.st_mode)}: soulctl writes only regular files (a new path or an existing file)")
        if not (st.st_mode & 0o222) or not os.access(target, os.W_OK):
            raise InputError(f"{option} {path} is read-only: soulctl does not overwrite it; choose another path or make it writable")
    _probe_folder(target.parent, option, path)
    return target


def check_output_folder(path: str | Path, option: str, files: Iterable[str] = ()) -> Path:
    """A folder that can be written, and the ``files`` the command will write in it.  A
    missing folder is created (with its missing parents, under a folder that exists) and
    belongs to the command's outputs: removed again unless they are committed."""
    p = Path(path)
    if not p.is_dir():
        _create_folder(p, option, path)
    _probe_folder(p, option, path)
    for name in files:
        check_output_path(p / name, option)
    return p


def _create_folder(folder: Path, option: str, path) -> None:
    missing = [folder]  # the folder and its missing parents, up to one that is a folder
    while not missing[-1].parent.is_dir() and missing[-1].parent != missing[-1]:
        missing.append(missing[-1].parent)
    existing = missing[-1].parent
    if os.path.lexists(missing[-1]) or (str(existing) and not existing.is_dir()):
        raise InputError(f"{option} must be a folder, got {path} (a file or link is in its place)")
    _probe_folder(existing, option, path)
    for f in reversed(missing):
        f.mkdir()
        current = _STAGE.get()
        if current is not None:
            current.created(f)


def _probe_folder(folder: Path, option: str, path) -> None:
    """Create and remove a temporary file in ``folder``: the only test that sees every reason
    (permissions, a read-only file system, a missing folder, a file where a folder should be)."""
    folder = folder if str(folder) else Path(".")
    try:
        fd, tmp = tempfile.mkstemp(prefix=".soulctl-probe-", dir=folder)
    except FileNotFoundError:
        raise InputError(f"{option}: cannot write {path}: the folder {folder} does not exist") from None
    except OSError as e:
        raise InputError(f"{option}: cannot write {path} (folder {folder}: {e.strerror or e})") from None
    os.close(fd)
    os.unlink(tmp)


class OutputStage:
    """Output files of one command, written under temporary names beside their targets and
    renamed onto them together by ``commit`` (or removed by ``discard``)."""

    def __init__(self) -> None:
        self._staged: dict[Path, str] = {}  # target -> temporary
        self._folders: list[Path] = []  # folders made for the outputs, parents first

    def created(self, folder: Path) -> None:
        self._folders.append(folder)

    def add(self, target: Path, tmp: str) -> None:
        old = self._staged.pop(target, None)
        if old is not None:
            _unlink(old)
        self._staged[target] = tmp

    def commit(self) -> None:
        while self._staged:
            target, tmp = next(iter(self._staged.items()))
            _replace(tmp, target)
            del self._staged[target]
        self._folders.clear()

    def discard(self) -> None:
        for tmp in self._staged.values():
            _unlink(tmp)
        self._staged.clear()
        for folder in reversed(self._folders):  # what the command made, if nothing else is in it
            try:
                folder.rmdir()
            except OSError:
                pass
        self._folders.clear()


_STAGE: ContextVar[OutputStage | None] = ContextVar("soulctl_output_stage", default=None)


@contextmanager
def staged_outputs():
    """Stage every ``atomic_write`` inside the block (see the module); the caller commits.
    Whatever is still staged when the block ends (an exception, an interrupt, no commit) is
    removed."""
    stage = OutputStage()
    token = _STAGE.set(stage)
    try:
        yield stage
    finally:
        _STAGE.reset(token)
        stage.discard()


def _unlink(tmp: str) -> None:
    try:
        os.unlink(tmp)
    except FileNotFoundError:
        pass


def _replace(tmp: str, target: Path) -> None:
    """Rename ``tmp`` onto ``target`` unless the target became something that must not be
    replaced since it was checked."""
    try:
        st = os.stat(target)
    except FileNotFoundError:
        st = None
    if st is not None and not stat.S_ISREG(st.st_mode):
        _unlink(tmp)
        raise InputError(f"{target} is {_kind(st.st_mode)}: soulctl writes only regular files")
    os.replace(tmp, target)


def atomic_write(path: str | Path, write: Callable[[str], None], *, immediate: bool = False) -> None:
    """Call ``write(tmp_path)`` to produce the file, then rename it onto ``path`` (through a
    symlink to its target; an existing file keeps its permission bits, a new one gets 0644).
    Inside ``staged_outputs`` the rename waits for the commit unless ``immediate``."""
    target, tmp = temporary_beside(path, ".tmp" + output_target(path).suffix)
    try:
        write(tmp)
        commit_or_replace(target, tmp, stage=not immediate)
    except BaseException:
        _unlink(tmp)
        raise


def temporary_beside(path: str | Path, suffix: str) -> tuple[Path, str]:
    """(the target of ``path``, a new empty temporary file beside it, named .soulctl-*suffix)
    with the mode the output will have: an existing file's permission bits, else 0644."""
    target = output_target(path)
    folder = target.parent if str(target.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=".soulctl-", suffix=suffix, dir=folder)
    try:
        try:
            mode = stat.S_IMODE(os.stat(target).st_mode)
        except FileNotFoundError:
            mode = NEW_FILE_MODE
        os.fchmod(fd, mode)
    except BaseException:
        _unlink(tmp)
        raise
    finally:
        os.close(fd)
    return target, tmp


def commit_or_replace(target: Path, tmp: str, stage: bool = True) -> None:
    """Land a file written under the temporary ``tmp`` (``atomic_write``'s last step for a
    writer that streamed into it): at the command's commit when ``stage`` and inside
    ``staged_outputs``, else at once (a partial telemetry file of an interrupted run)."""
    current = _STAGE.get() if stage else None
    if current is None:
        _replace(tmp, target)
    else:
        current.add(target, tmp)


def atomic_write_text(path: str | Path, text: str, *, immediate: bool = False) -> None:
    def write(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(text)

    atomic_write(path, write, immediate=immediate)
