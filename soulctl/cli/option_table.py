"""Typer commands declared as an option table and a body.

A command with thirty options written in Typer's usual style is a function whose signature
alone is longer than its logic.  Here the options are data: a dataclass whose fields are the
command's parameters, each with its type and, as its default, the ``typer.Option`` that
declares it (help, range parser, default).  ``command(Options)`` turns a body taking one
``Options`` value into the function Typer introspects: same parameters, same help text, so
the command line, ``--help`` and the option checks are exactly those of the usual style.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect
import typing
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")


def command(options: type[T]) -> Callable[[Callable[[T], int]], Callable[..., int]]:
    """Decorator: the body ``f(o: options) -> int`` as a Typer command whose parameters are
    the fields of the dataclass ``options`` (in their order; defaults are the Typer options)."""
    hints = typing.get_type_hints(options)
    fields = dataclasses.fields(options)  # type: ignore[arg-type]
    parameters = [inspect.Parameter(f.name, inspect.Parameter.KEYWORD_ONLY, default=f.default, annotation=hints[f.name]) for f in fields]

    def decorate(body: Callable[[T], int]) -> Callable[..., int]:
        @functools.wraps(body)
        def typer_command(**values: Any) -> int:
            return body(options(**values))

        typer_command.__signature__ = inspect.Signature(parameters, return_annotation=int)  # type: ignore[attr-defined]
        typer_command.__annotations__ = {p.name: p.annotation for p in parameters} | {"return": int}
        del typer_command.__wrapped__  # Typer must see the table's parameters, not the body's
        return typer_command

    return decorate
