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
import sys
import unicodedata

from rich.console import Console
from rich.text import Text

ERRORS = "soulctl-ascii"
_ASCII = {
    "λ": "lambda", "χ": "chi", "γ": "gamma", "ζ": "zeta", "Λ": "Lambda", "Δ": "Delta", "Ξ": "Xi", "Σ": "Sigma", "ν": "nu",
    "ρ": "rho", "ε": "epsilon", "α": "alpha", "β": "beta", "µ": "u", "μ": "u", "″": '"', "′": "'", "°": " deg",
    "≤": "<=", "≥": ">=", "→": "->", "←": "<-", "×": "x", "·": ".", "…": "...", "—": "-", "–": "-", "−": "-",
    "∞": "inf", "∏": "prod", "⁻": "^-", "¹": "1", "²": "2", "³": "3", "√": "sqrt", "±": "+/-", "≈": "~",
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


def console(stderr: bool = False) -> Console:
    """A rich console that prints text as given (no markup, no emoji codes)."""
    return Console(stderr=stderr, markup=False, emoji=False, highlight=False)


def styled(text: str, style: str) -> Text:
    """``text`` in a rich style (e.g. "bold red"), the way to colour output without markup."""
    return Text(text, style=style)
