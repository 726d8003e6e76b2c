"""Per-mode gain files: what `optimize gains --out` writes and `loop run --gains FILE` reads.

Formats read (one gain per controlled mode, mode 1 = Tip):

* TOML: ``gains = [g1, g2, ...]`` (what soulctl writes);
* text/CSV: one gain per line, or ``mode,gain`` lines, with an optional header row naming the
  columns (``mode,gain`` or ``gain``); lines starting with '#' are comments.  Where modes are
  given, the gains are placed by their mode number, whatever the order of the lines; every
  mode from 1 to the last must appear exactly once.

Every gain must be in ``ranges.LOOP_GAIN``; the loop's stability check comes after.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import read_input_text, read_toml
from ..ranges import LOOP_GAIN, number_text

SUFFIXES = (".toml", ".txt", ".csv", ".dat")


def read_gain_file(path: str | Path) -> np.ndarray:
    """The per-mode gains of a gain file (see the module); InputError naming the file and line."""
    p = Path(path)
    if p.suffix.lower() == ".toml":
        values = read_toml(p, "gain file").get("gains")
        if not isinstance(values, list) or not values:
            raise InputError(f"gain file {p} needs a list 'gains = [...]' with one gain per mode")
        gains = [_gain(v, p, f"gains[{i}]") for i, v in enumerate(values)]
    else:
        gains = _text_gains(read_input_text(p, "gain file"), p)
    return np.array(gains, dtype=float)


def _gain(value, path: Path, where: str) -> float:
    if isinstance(value, str):
        try:
            value = float(value)
        except ValueError:
            raise InputError(f"gain file {path}, {where}: a gain must be a number in {LOOP_GAIN.text()}, got '{value}'") from None
    if not LOOP_GAIN.contains(value):
        raise InputError(f"gain file {path}, {where}: a gain must be a number in {LOOP_GAIN.text()}, got {number_text(value)}")
    return float(value)


def _text_gains(text: str, path: Path) -> list[float]:
    numbered = [(i + 1, line) for i, line in enumerate(text.splitlines()) if line.strip() and not line.lstrip().startswith("#")]
    if not numbered:
        raise InputError(f"gain file {path} holds no gains (one per line, or mode,gain lines)")
    rows = [(n, [c.strip() for c in row]) for (n, _), row in zip(numbered, csv.reader(line for _, line in numbered))]
    header = [c.lower() for c in rows[0][1]]
    columns: dict[str, int | None] = {"gain": len(header) - 1, "mode": 0 if len(header) == 2 else None}
    if not _is_number(rows[0][1][-1]):
        if "gain" not in header or set(header) - {"mode", "gain"}:
            raise InputError(f"gain file {path}, line {rows[0][0]}: the header must name the columns mode,gain or gain, got {rows[0][1]}")
        columns = {"gain": header.index("gain"), "mode": header.index("mode") if "mode" in header else None}
        rows = rows[1:]
    width = 1 + (columns["mode"] is not None)
    gains, modes = [], []
    for n, row in rows:
        if len(row) != width:
            raise InputError(f"gain file {path}, line {n}: expected {'mode,gain' if width == 2 else 'one gain'}, got {row}")
        gain_column, mode_column = columns["gain"], columns["mode"]
        assert gain_column is not None
        gains.append(_gain(row[gain_column], path, f"line {n}"))
        if mode_column is not None:
            modes.append(_mode(row[mode_column], path, n))
    return gains if not modes else _by_mode(gains, modes, path)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _mode(text: str, path: Path, line: int) -> int:
    try:
        return int(text)
    except ValueError:
        raise InputError(f"gain file {path}, line {line}: the mode must be an integer >= 1, got '{text}'") from None


def _by_mode(gains: list[float], modes: list[int], path: Path) -> list[float]:
    """Gains ordered by mode number; every mode 1..n exactly once."""
    if sorted(modes) != list(range(1, len(modes) + 1)):
        raise InputError(
            f"gain file {path}: the modes must be 1..{len(modes)}, each once (got {len(set(modes))} distinct, "
            f"from {min(modes)} to {max(modes)})"
        )
    out = [0.0] * len(gains)
    for m, g in zip(modes, gains):
        out[m - 1] = g
    return out


def gains_toml(gains: np.ndarray, comment: str) -> str:
    """A gain file `loop run --gains` reads: ``gains = [...]``, one per mode."""
    body = ",\n".join("  " + ", ".join(f"{g:.5f}" for g in gains[i : i + 8]) for i in range(0, len(gains), 8))
    lines = " ".join(comment.splitlines())
    return f"# {lines}\n# one gain per mode (mode 1 = Tip); use with: soulctl loop run --gains FILE\ngains = [\n{body},\n]\n"
