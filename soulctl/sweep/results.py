"""The results table of a sweep: one CSV row per case, the whole file rewritten atomically
(temporary file, then rename) each time a case finishes, so that an interrupted sweep leaves
the rows finished so far and never a half-written one.  `--resume` reads it back and skips
the cases whose row is there (status ok or diverged; failed cases are run again); rows of
other grids in the file are kept as they are."""

from __future__ import annotations

import csv
import io
import math
from pathlib import Path

from ..errors import InputError
from ..files import atomic_write_text
from .case import DEFAULTS, METRICS
from .grid import PARAMETERS

COLUMNS = ("case_id", *PARAMETERS, *METRICS, "status", "reason", "run_seconds", "soulctl_version")
FINISHED = ("ok", "diverged")
FLOATS = {name for name, p in PARAMETERS.items() if p.kind is float} | set(METRICS) | {"run_seconds"}
INTS = {name for name, p in PARAMETERS.items() if p.kind is int}
BOOLS = {name for name, p in PARAMETERS.items() if p.kind is bool}


def _text(value) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return repr(value) if isinstance(value, float) else str(value)


def _value(name: str, text: str):
    if text == "":
        return float("nan") if name in METRICS else None
    if name in FLOATS:
        return float(text)
    if name in INTS:
        return int(text)
    if name in BOOLS:
        return text == "True"
    return text


class ResultsTable:
    """Rows by case id, written to ``path`` (CSV) in the order of the grid's cases."""

    def __init__(self, path: Path, order: list[str]):
        self.path = Path(path)
        self.order = {cid: i for i, cid in enumerate(order)}
        self.rows: dict[str, dict] = {}

    @staticmethod
    def read_rows(path: Path) -> dict[str, dict]:
        """The rows of an existing results file, by case id; InputError if it is not one."""
        try:
            with open(path, newline="") as f:
                reader = csv.DictReader(f)
                if reader.fieldnames is None or "case_id" not in reader.fieldnames:
                    raise InputError(f"{path} is not a sweep results file (no case_id column)")
                rows = {}
                for r in reader:
                    try:
                        rows[r["case_id"]] = {k: _value(k, v) for k, v in r.items() if k in COLUMNS}
                    except (TypeError, ValueError):
                        raise InputError(f"results file {path}, line {reader.line_num}: not a row of a sweep "
                                         f"(missing or malformed values)") from None
                return rows
        except (OSError, UnicodeDecodeError, csv.Error) as e:
            raise InputError(f"cannot read the results file {path}: {e}") from None

    def resume(self) -> set[str]:
        """Load the existing file's rows (all kept, other grids' included, after this grid's);
        the case ids of this grid whose rows are finished (failed ones run again)."""
        if not self.path.exists():
            return set()
        rows = self.read_rows(self.path)
        self.rows.update(rows)
        return {cid for cid, r in rows.items() if cid in self.order and r.get("status") in FINISHED}

    def add(self, row: dict) -> None:
        self.rows[row["case_id"]] = row
        self.write()

    def write(self) -> None:
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\n")
        writer.writerow(COLUMNS)
        for cid in sorted(self.rows, key=lambda c: self.order.get(c, len(self.order))):
            row = {**DEFAULTS, **self.rows[cid]}
            writer.writerow([_text(row.get(c)) for c in COLUMNS])
        atomic_write_text(self.path, out.getvalue())
