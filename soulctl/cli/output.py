"""What the command line prints, and how: one console factory and the terminal's encoding.

Every console is made by ``console()``: rich markup and emoji codes are off, so that text a
user gave (a label, a path holding ``[/]`` or ``:smile:``) prints as it is and never breaks or
restyles the output; styles are given as ``rich.text.Text`` objects instead.

A terminal or pipe whose encoding is not UTF-8 (``PYTHONIOENCODING=ascii``, a C locale) gets
ASCII: rich draws its tables with ASCII boxes by itself, and ``ascii_fallback`` transliterates
the other characters (λ -> lambda, χ -> chi, ″ -> ", Kármán -> Karman, ...) instead of failing.
"""

from __future__ import annotations

import codecs
import json
import math
import os
import sys
import unicodedata

import typer
from rich.console import Console
from rich.text import Text

ERRORS = "soulctl-ascii"
JSON_OUTPUT = typer.Option(False, "--json", help="Print one JSON object instead of the table.")  # every command's
_ASCII = {
    "λ": "lambda",
    "χ": "chi",
    "γ": "gamma",
    "ζ": "zeta",
    "Λ": "Lambda",
    "Δ": "Delta",
    "Ξ": "Xi",
    "Σ": "Sigma",
    "ν": "nu",
    "ρ": "rho",
    "ε": "epsilon",
    "α": "alpha",
    "β": "beta",
    "µ": "u",
    "μ": "u",
    "″": '"',
    "′": "'",
    "°": " deg",
    "≤": "<=",
    "≥": ">=",
    "→": "->",
    "←": "<-",
    "×": "x",
    "·": ".",
    "…": "...",
    "—": "-",
    "–": "-",
    "−": "-",
    "∞": "inf",
    "∏": "prod",
    "⁻": "^-",
    "¹": "1",
    "²": "2",
    "³": "3",
    "√": "sqrt",
    "±": "+/-",
    "≈": "~",
}


def _transliterate(error: UnicodeError):
    if not isinstance(error, UnicodeEncodeError):
        raise error
    out = []
    for ch in error.object[error.start : error.end]:
        if ch in _ASCII:
            out.append(_ASCII[ch])
            continue
        plain = unicodedata.normalize("NFKD", ch).encode("ascii", "ignore").decode()
        out.append(plain or "?")
    return "".join(out), error.end


codecs.register_error(ERRORS, _transliterate)


def ascii_fallback() -> None:
    """Let stdout and stderr degrade to ASCII where their encoding cannot say everything."""
    for stream in (sys.stdout, sys.stderr):
        encoding = (getattr(stream, "encoding", None) or "").lower().replace("_", "-")
        if encoding.startswith("utf") or not hasattr(stream, "reconfigure"):
            continue
        try:
            stream.reconfigure(errors=ERRORS)
        except (ValueError, OSError):  # a stream that cannot be reconfigured (closed, replaced by a test)
            pass


def _utf(stream) -> bool:
    return (getattr(stream, "encoding", None) or "utf-8").lower().replace("_", "-").startswith("utf")


def ascii_text(text: str) -> str:
    """``text`` with every character ASCII cannot hold transliterated (see the module)."""
    return text.encode("ascii", errors=ERRORS).decode("ascii")


class _Console(Console):
    """rich's console, except that a reader going away (``| head``) is a BrokenPipeError for
    the entry point to handle (rich would exit the process with status 1)."""

    def on_broken_pipe(self) -> None:
        raise BrokenPipeError()


class _AsciiConsole(_Console):
    """A console for a stream that is not UTF-8: text is transliterated before rich lays it
    out, so that tables are measured on what is printed (λ -> lambda is 6 columns, not 1)."""

    def render_str(self, text: str, **kwargs) -> Text:
        return super().render_str(ascii_text(text), **kwargs)


PIPE_COLUMNS = 160  # the width of a table written to a pipe or a file (rich's own default: 80)


def console(stderr: bool = False) -> Console:
    """A rich console that prints text as given (no markup, no emoji codes, lines not broken:
    a path stays on one line; tables still fit the terminal), in ASCII where the stream is not
    UTF-8.  Into a pipe or a file (no terminal, no COLUMNS), tables are laid out on PIPE_COLUMNS
    columns, so that ``soulctl ... | grep`` finds a row on one line."""
    stream = sys.stderr if stderr else sys.stdout
    kind = _Console if _utf(stream) else _AsciiConsole
    piped = not (hasattr(stream, "isatty") and stream.isatty()) and "COLUMNS" not in os.environ
    return kind(stderr=stderr, markup=False, emoji=False, highlight=False, soft_wrap=True, width=PIPE_COLUMNS if piped else None)


def figure_text(value: float, digits: int = 3) -> str:
    """A measured or derived number to its meaningful digits, the one rule of the tables and
    captions: ``digits`` significant (numbers of ``digits`` or more integer digits whole),
    trailing zeros dropped, an exponent only below 1e-3 (0.673798 -> 0.674, 2.73348 -> 2.73,
    8.0 -> 8, 1148.3 -> 1148, 0.5 -> 0.5).  Values a user gave are echoed as given
    (``ranges.number_text``)."""
    if not math.isfinite(value):
        return "n/a"
    if abs(value) >= 10 ** (digits - 1):
        return f"{value:.0f}"
    rounded = float(f"{value:.{digits}g}")
    if rounded == 0 or abs(rounded) >= 1e-3:
        order = math.floor(math.log10(abs(rounded))) if rounded else 0
        text = f"{rounded:.{max(0, digits - 1 - order)}f}"
        return text.rstrip("0").rstrip(".") if "." in text else text
    return f"{rounded:.{digits - 1}e}"


def styled(text: str, style: str) -> Text:
    """``text`` in a rich style (e.g. "bold red"), the way to colour output without markup."""
    return Text(text if _utf(sys.stdout) else ascii_text(text), style=style)


def json_safe(value):
    """``value`` with every NaN or infinite float replaced by None (not available) and numpy
    scalars and arrays made plain: JSON that every parser reads (no NaN/Infinity tokens)."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):  # numpy arrays and scalars
        return json_safe(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def print_json(value) -> None:
    """One JSON object on stdout (``json_safe``; a value JSON cannot hold is a bug, not output)."""
    print(json.dumps(json_safe(value), allow_nan=False))


def warn(text: str) -> None:
    """One line on stderr: what a figure printed cannot tell (its validity), never an error."""
    print("soulctl: warning: " + " ".join(str(text).split()), file=sys.stderr)
