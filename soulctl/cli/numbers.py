"""How the command line reads a number: one parser for every numeric option, so that every
option reads numbers as ``soulctl.ranges`` describes (Python's syntax: Unicode decimal digits
are digits, ``1_000`` is 1000; an integer option takes ``3`` or ``3.0``, never ``3.5``), and a
text that is not a number is refused with the option's accepted range.  The range itself is
checked by the command (one message, "--X must be in ..., got ...", for every command)."""

from __future__ import annotations

import math
from collections.abc import Callable

import typer

from .. import tables
from ..errors import InputError
from ..ranges import Range

_EXACT_FLOAT_INTEGERS = 2**53  # above, a float no longer holds every integer


def _integer(text: str) -> int | None:
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        return None
    return int(value) if math.isfinite(value) and value.is_integer() and abs(value) < _EXACT_FLOAT_INTEGERS else None


def number(accepted: Range, option: str | None = None) -> Callable[[str], float | int]:
    """A typer ``parser=`` for an option whose values are in ``accepted`` (ints for an integer
    range, floats otherwise); given the ``option``'s name, it also checks the range (one line
    naming the option and the range, before the command's body runs)."""

    def parse(text):
        if isinstance(text, (int, float)) and not isinstance(text, bool):  # a default
            return text
        text = str(text).strip()
        value: float | int | None
        if accepted.integer:
            value = _integer(text)
        else:
            try:
                value = float(text)
            except ValueError:
                value = None
        if value is None:
            kind = "an integer" if accepted.integer else "a number"
            raise typer.BadParameter(f"must be {kind} in {accepted.text()}, got '{text}'")
        if option is None:
            return value
        try:
            return accepted.check(value, option)  # the range's own message, without the name click adds
        except InputError as e:
            raise typer.BadParameter(str(e).removeprefix(f"{option} ")) from None

    return parse


def magnitude_option(default=None, show_default: str | bool = False):
    """--mag, declared once: the guide star whose look-up table row sets the configuration
    (binning, modes, frame rate, modulation, filters), parsed by ``parse_magnitude``."""
    return typer.Option(
        default,
        "--mag",
        metavar="R",
        show_default=show_default,
        help="Guide star R magnitude (0 to 18.5): the look-up table's binning, modes, frame rate, modulation and filters.",
    )


def parse_magnitude(text: str) -> float:
    """The --mag value as a finite number inside the look-up table's range."""
    lo, hi = tables.magnitude_range(tables.magnitude_table())
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise InputError(f"--mag must be a number, got '{text}': accepted range {lo:g} <= R <= {hi:g}")
    return value + 0.0  # -0 -> 0; the range is checked against the table's rows
