"""The results table of a sweep, DIR/results.csv: a header line, then one CSV line per case.

Writing.  Rows are appended as the cases finish, in finishing order: each row is one write of
a complete line to the file opened in append mode, synced to disk, so that an interrupted
sweep leaves every row finished so far and at most one incomplete last line (a crash in the
middle of a write), which the next ``--resume`` ignores and truncates.  A case that runs again
(a failed case on ``--resume``) appends a new row: the last row of a case id is its row.  When
a run has given every case of its grid a row, the file is rewritten once, atomically (a
temporary file renamed onto it), in the grid's order, one row per case id (rows of other grids
after them, in their order).  While it writes, a sweep holds a lock on DIR/.results.csv.lock
(``flock``): a second sweep into the same folder is refused.

Reading (``--resume``).  The file is read as soulctl reads every input (a regular file, UTF-8
with or without a byte-order mark, at most ``MAX_RESULTS_BYTES``).  Every row is checked: the
number of fields, each parameter in its range (``grid.PARAMETERS``), the status, finite metrics
for an ``ok`` row, and for a case of the grid being resumed, its parameters equal to the
case's; a row that fails is an InputError naming its line (the file was edited: correct or
delete the row, or set its status to failed to run the case again).  Columns that are not
soulctl's are kept (new rows leave them empty); a missing soulctl column is refused.  The
cases whose row is finished (ok or diverged) are skipped; failed ones run again.
"""

from __future__ import annotations

import codecs
import csv
import errno
import fcntl
import io
import math
import os
import stat
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import InputError
from ..files import NEW_FILE_MODE, atomic_write_text, output_target, read_input_bytes
from .case import DEFAULTS, METRICS, STATUS
from .grid import PARAMETERS, case_id

COLUMNS = ("case_id", *PARAMETERS, *METRICS, "status", "reason", "run_seconds", "soulctl_version")
FINISHED = ("ok", "diverged")
FLOATS = {name for name, p in PARAMETERS.items() if p.kind is float} | set(METRICS) | {"run_seconds"}
INTS = {name for name, p in PARAMETERS.items() if p.kind is int}
BOOLS = {name for name, p in PARAMETERS.items() if p.kind is bool}
OPTIONAL = {name for name in PARAMETERS if name not in DEFAULTS and name != "magnitude"}  # empty: the look-up table's
MAX_RESULTS_BYTES = 256 * 2**20  # ~1 million rows; a grid has at most grid.MAX_CASES cases
LOCK_NAME = ".results.csv.lock"


def _text(value) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return repr(value) if isinstance(value, float) else str(value)


def _value(name: str, text: str):
    """A field as the row holds it; ValueError when it is not of the column's kind."""
    if text == "":
        return float("nan") if name in METRICS else None
    if name in FLOATS:
        return float(text)
    if name in INTS:
        try:
            return int(text)
        except ValueError:
            x = float(text)  # "4.0", as a spreadsheet may write it
            if not x.is_integer():
                raise
            return int(x)
    if name in BOOLS:
        if text.lower() not in ("true", "false"):
            raise ValueError(text)
        return text.lower() == "true"
    return text


def _kind(name: str) -> str:
    return "a number" if name in FLOATS else "an integer" if name in INTS else "true or false" if name in BOOLS else "text"


def _csv_line(fields: list[str]) -> str:
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerow(fields)
    return out.getvalue()


def csv_line(row: dict, columns) -> str:
    """One CSV line (ending in a line feed) of ``row`` in ``columns``' order; the reason on one
    line (an error message may hold line ends), so that every row is one physical line."""
    row = {**DEFAULTS, **row}
    return _csv_line([" ".join(_text(row.get(c)).split()) if c == "reason" else _text(row.get(c)) for c in columns])


def header_line(columns) -> str:
    return _csv_line(list(columns))


@dataclass
class ResultsContent:
    """An existing results file as read back (see the module)."""

    columns: tuple[str, ...]
    rows: dict[str, dict] = field(default_factory=dict)  # the last row of each case id, in file order
    lines: dict[str, int] = field(default_factory=dict)  # its line number
    complete_bytes: int = 0  # the length of the file's complete lines: appending starts there
    ends_with_newline: bool = True  # else the next row starts with a line end
    notes: list[str] = field(default_factory=list)


def read_results(path: str | Path, cases: dict[str, dict] | None = None) -> ResultsContent:
    """Read and check a results file (see the module); ``cases``: the grid being resumed, by
    case id, whose rows must hold their case's parameters."""
    path = Path(path)
    where = f"results file {path}"
    raw = read_input_bytes(path, "results file", MAX_RESULTS_BYTES)
    start = len(codecs.BOM_UTF8) if raw.startswith(codecs.BOM_UTF8) else 0
    cut = raw.rfind(b"\n") + 1
    cut = max(cut, start)
    try:
        head = raw[start:cut].decode("utf-8")
    except UnicodeDecodeError:
        raise InputError(f"{where} is not UTF-8 text") from None
    records = _records(head, where)
    tail = raw[cut:]
    tail_record = None
    if tail:
        try:
            tail_records = _records(tail.decode("utf-8"), where)
            tail_record = tail_records[0] if len(tail_records) == 1 else None
        except (UnicodeDecodeError, InputError):
            tail_record = None
        tail_line = head.count("\n") + 1
    if not records:
        if tail_record is not None and _is_header(tail_record[1]):  # a header without its line end: no rows
            content = ResultsContent(_header(tail_record[1], where), complete_bytes=len(raw), ends_with_newline=False)
            return content
        if tail or start:  # an interrupted first write (the header): start again
            return ResultsContent(
                COLUMNS, complete_bytes=0, notes=[f"{where}: the incomplete header line (an interrupted write) is ignored"] if tail else []
            )
        return ResultsContent(COLUMNS, complete_bytes=0)
    columns = _header(records[0][1], where)
    content = ResultsContent(columns, complete_bytes=cut)
    grid_fields = {name for case in (cases or {}).values() for name in case}
    extra = [c for c in columns if c not in COLUMNS and c not in grid_fields]
    if extra:
        content.notes.append(f"{where}: the columns {', '.join(extra)} are not soulctl's: kept, empty in new rows")
    for line, fields in records[1:]:
        _add_row(content, _row(fields, columns, line, where, cases), line)
    if tail:
        try:
            if tail_record is None:
                raise InputError("incomplete")
            row = _row(tail_record[1], columns, tail_line, where, cases)
        except InputError:
            content.notes.append(
                f"{where}, line {tail_line}: an incomplete last row (an interrupted write) is ignored and removed; its case runs again"
            )
        else:  # a complete row without its line end (e.g. saved by a spreadsheet)
            _add_row(content, row, tail_line)
            content.complete_bytes = len(raw)
            content.ends_with_newline = False
    return content


def _add_row(content: ResultsContent, row: dict, line: int) -> None:
    cid = row["case_id"]
    content.rows.pop(cid, None)  # the last row of a case id is its row (and keeps its place at the end)
    content.rows[cid] = row
    content.lines[cid] = line


def _records(text: str, where: str) -> list[tuple[int, list[str]]]:
    """(line number, fields) of the non-blank records of ``text``; InputError naming the line."""
    reader = csv.reader(io.StringIO(text, newline=""), strict=True)
    out = []
    try:
        for fields in reader:
            if any(f.strip() for f in fields):
                out.append((reader.line_num, fields))
    except csv.Error as e:
        raise InputError(f"{where}, line {reader.line_num}: not CSV ({e})") from None
    return out


def _is_header(fields: list[str]) -> bool:
    return "case_id" in fields and not (set(COLUMNS) - set(fields))


def _header(fields: list[str], where: str) -> tuple[str, ...]:
    if "case_id" not in fields:
        raise InputError(f"{where} is not a sweep results file (no case_id column)")
    dup = sorted({f for f in fields if fields.count(f) > 1})
    if dup:
        raise InputError(f"{where}: the column {', '.join(dup)} appears more than once")
    missing = [c for c in COLUMNS if c not in fields]
    if "wfs_field" in missing and "oversampling" in fields:
        raise InputError(
            f"{where} lacks the column wfs_field: it was written before SOUL's 2.1\" field of view became the default and "
            "its rows ran the sampled field, which the grid's cases no longer are: choose another --out"
        )
    if missing:
        raise InputError(
            f"{where} lacks the columns {', '.join(missing)} of a soulctl results file "
            f"(from another version?): complete it or choose another --out"
        )
    return tuple(fields)


def _row(fields: list[str], columns: tuple[str, ...], line: int, where: str, cases: dict[str, dict] | None) -> dict:
    """A checked row (see the module); InputError naming the line."""
    at = f"{where}, line {line}"
    if len(fields) != len(columns):
        raise InputError(f"{at}: {len(fields)} fields where the header has {len(columns)}")
    row = _parsed(fields, columns, at)
    if not row["case_id"]:
        raise InputError(f"{at}: the case_id is empty")
    if row["status"] not in STATUS:
        raise InputError(f"{at}: status must be {', '.join(STATUS[:-1])} or {STATUS[-1]}, got '{row['status'] or ''}'")
    _check_parameters(row, at)
    _check_metrics(row, dict(zip(columns, fields)), at)
    case = (cases or {}).get(row["case_id"])
    if case is not None:
        _check_against_case(row, {**DEFAULTS, **case}, at)
    return row


def _parsed(fields: list[str], columns: tuple[str, ...], at: str) -> dict:
    """Each known column's value parsed (unknown columns kept as text)."""
    row: dict = {}
    for name, text in zip(columns, fields):
        if name not in COLUMNS:
            row[name] = text  # kept as it is
            continue
        try:
            row[name] = _value(name, text.strip())
        except ValueError:
            raise InputError(f"{at}: {name} must be {_kind(name)}, got '{text}'") from None
    return row


def _check_parameters(row: dict, at: str) -> None:
    """Every parameter given (or optional) and in its range, checked in place."""
    for name, p in PARAMETERS.items():
        if row[name] is None:
            if name not in OPTIONAL:
                raise InputError(f"{at}: {name} is empty")
            continue
        try:
            row[name] = p.check(row[name], name)
        except InputError as e:
            raise InputError(f"{at}: {e}") from None


def _check_metrics(row: dict, texts: dict[str, str], at: str) -> None:
    """An ok row has finite metrics; any row's metrics are finite or empty; run_seconds >= 0."""
    for name in METRICS:
        empty = texts[name].strip() == ""
        if row["status"] == "ok" and not math.isfinite(row[name]):
            raise InputError(
                f"{at}: status ok with {'an empty' if empty else 'a non-finite'} {name} (an ok row needs "
                f"finite {', '.join(METRICS)}): correct or delete the row, or set its status to failed to run it again"
            )
        if not empty and not math.isfinite(row[name]):
            raise InputError(f"{at}: {name} must be a finite number or empty, got '{texts[name]}'")
    if row["run_seconds"] is not None and not (math.isfinite(row["run_seconds"]) and row["run_seconds"] >= 0):
        raise InputError(f"{at}: run_seconds must be a finite number >= 0, got {row['run_seconds']}")


def _check_against_case(row: dict, expected: dict, at: str) -> None:
    """The row's parameters are its grid case's."""
    for name in PARAMETERS:
        if row[name] != expected.get(name):
            raise InputError(
                f"{at}: the row of case {row['case_id']} has {name} = {_text(row[name]) or 'empty'} where the "
                f"grid's case has {_text(expected.get(name)) or 'none'}: correct or delete the row"
            )


# -------------------------------------------------------------------------------- the lock


def columns_of(cases: list[dict]) -> tuple[str, ...]:
    """The results' columns: soulctl's, then the grid's run description fields by dotted name."""
    dotted = dict.fromkeys(name for case in cases for name in case if name not in COLUMNS)
    i = COLUMNS.index("strehl")
    return (*COLUMNS[:i], *dotted, *COLUMNS[i:])


def lock_path(folder: str | Path) -> Path:
    return Path(folder) / LOCK_NAME


def check_unlocked(folder: str | Path) -> None:
    """InputError if a sweep holds the lock of ``folder`` (creates nothing)."""
    path = lock_path(folder)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC | os.O_NONBLOCK)
    except OSError:
        return  # no lock file: no sweep is writing there
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise InputError(f"--out: {path} is not a regular file: soulctl keeps its lock there; remove it")
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        raise InputError(_locked_message(folder, fd)) from None
    except OSError:
        pass  # a file system without flock: the lock itself will say
    finally:
        os.close(fd)


def _locked_message(folder, fd: int) -> str:
    try:
        pid = os.pread(fd, 32, 0).decode().strip()
    except (OSError, UnicodeDecodeError):
        pid = ""
    who = f"process {pid}" if pid.isdigit() else "another process"
    return (
        f"another soulctl sweep ({who}) is writing {Path(folder) / 'results.csv'}: wait for it to end, or choose "
        f"another --out (a sweep holds {lock_path(folder)} while it runs)"
    )


@contextmanager
def results_lock(folder: str | Path):
    """Hold the lock of ``folder`` (non-blocking: InputError if a sweep holds it); the lock
    file is removed when released."""
    path = lock_path(folder)
    while True:
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | os.O_NONBLOCK, NEW_FILE_MODE)
        except OSError as e:
            raise InputError(f"--out: cannot create the lock {path}: {e.strerror or e}") from None
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                raise InputError(f"--out: {path} is not a regular file: soulctl keeps its lock there; remove it")
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            message = _locked_message(folder, fd)
            os.close(fd)
            raise InputError(message) from None
        except OSError as e:
            os.close(fd)
            raise InputError(f"--out: cannot lock {path}: {e.strerror or e}") from None
        except BaseException:
            os.close(fd)
            raise
        try:  # the file may have been removed by the sweep that held it: lock the one at the path
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield path
    finally:
        try:
            os.unlink(path)  # while still locked: a sweep waiting for it then locks a new file
        except FileNotFoundError:
            pass
        os.close(fd)


# ------------------------------------------------------------------------------- the table


class ResultsTable:
    """The results of a grid (``cases``), rows by case id, written to ``path`` (see the module)."""

    def __init__(self, path: str | Path, cases: list[dict]):
        self.path = Path(path)
        self.cases = {case_id(c): c for c in cases}
        self.order = {cid: i for i, cid in enumerate(self.cases)}
        self.columns: tuple[str, ...] = columns_of(cases)
        self.rows: dict[str, dict] = {}
        self.notes: list[str] = []
        self._content: ResultsContent | None = None
        self._fd: int | None = None
        self._newline = False

    @staticmethod
    def read_rows(path: str | Path) -> dict[str, dict]:
        """The rows of an existing results file, by case id (checked: see the module)."""
        return read_results(path).rows

    def resume(self) -> set[str]:
        """Load the existing file's rows (all kept, other grids' included, after this grid's);
        the case ids of this grid whose rows are finished (failed ones run again)."""
        if not os.path.lexists(self.path):
            self._content = None
            return set()
        self._content = read_results(self.path, self.cases)
        missing = [c for c in self.columns if c not in self._content.columns]
        if missing:
            raise InputError(f"{self.path} has no column {missing[0]} for the grid's parameter of that name: choose another --out")
        self.columns = self._content.columns
        self.rows = dict(self._content.rows)
        self.notes = list(self._content.notes)
        return {cid for cid, r in self.rows.items() if cid in self.order and r["status"] in FINISHED}

    def open(self) -> None:
        """Open the file for appending (after ``resume``, under the lock): created with its
        header when new, an incomplete last line truncated."""
        target = output_target(self.path)
        created = not os.path.lexists(target)
        fd = os.open(target, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC | os.O_NONBLOCK, NEW_FILE_MODE)
        try:
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode):
                raise InputError(f"{self.path} is not a regular file: soulctl writes only regular files")
            fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~os.O_NONBLOCK)
            if created:
                os.fchmod(fd, NEW_FILE_MODE)
            keep = self._content.complete_bytes if self._content is not None else 0
            if st.st_size > keep:
                os.ftruncate(fd, keep)
            self._fd = fd
            if keep == 0:
                self._write(header_line(self.columns))
            self._newline = self._content is not None and not self._content.ends_with_newline and keep > 0
        except BaseException:
            os.close(fd)
            self._fd = None
            raise

    def add(self, row: dict) -> None:
        """Append ``row`` (one write of a complete line)."""
        self.rows.pop(row["case_id"], None)
        self.rows[row["case_id"]] = row
        line = csv_line(row, self.columns)
        if self._newline:
            line = "\n" + line
        self._write(line)
        self._newline = False

    def _write(self, text: str) -> None:
        data = text.encode("utf-8")
        fd = self._fd
        assert fd is not None  # open between start and close
        size = os.fstat(fd).st_size
        try:
            n = os.write(fd, data)
            if n != len(data):
                raise OSError(errno.ENOSPC, f"short write to {self.path} ({n} of {len(data)} bytes)")
            os.fdatasync(fd)
        except BaseException:
            try:
                os.ftruncate(fd, size)  # no partial line is left behind
            except OSError:
                pass
            raise

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def write_ordered(self) -> None:
        """Rewrite the file at once (atomically, not staged): the grid's order, one row per
        case id, other grids' rows after them."""
        self.close()
        lines = [header_line(self.columns)]
        for cid in sorted(self.rows, key=lambda c: self.order.get(c, len(self.order))):
            lines.append(csv_line(self.rows[cid], self.columns))
        atomic_write_text(self.path, "".join(lines), immediate=True)
