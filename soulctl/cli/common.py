"""What several command groups share: the --config/--mag observation, the calibration cache
options, and the two-column quantity/value table."""

from __future__ import annotations

import os
from pathlib import Path

import typer
from rich.table import Table

from ..errors import InputError
from ..observation import Observation, observation_for_magnitude
from ..optics.cache import ArrayCache
from .configure import parse_magnitude

CONFIG = typer.Option(None, "--config", metavar="FILE", help="Observation TOML (from 'soulctl configure --out').")
NO_CACHE = typer.Option(False, "--no-cache", help="Recompute and do not store (the cache is otherwise reused).")
CACHE_DIR = typer.Option(None, "--cache-dir", metavar="DIR", help="Cache folder (default $XDG_CACHE_HOME/soulctl or ~/.cache/soulctl).")


def default_cache_dir() -> Path:
    """$XDG_CACHE_HOME/soulctl, else ~/.cache/soulctl."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "soulctl"


def array_cache(no_cache: bool, cache_dir: Path | None) -> ArrayCache:
    """The calibration cache the options ask for (disabled with --no-cache)."""
    return ArrayCache(None if no_cache else (cache_dir or default_cache_dir()))


def observation_option(config: Path | None, mag: str | None) -> Observation | None:
    """The observation of --config or --mag (never both); None without either."""
    if config is not None and mag is not None:
        raise InputError("give either --config or --mag, not both")
    if config is not None:
        return Observation.read_toml(config)
    if mag is not None:
        return observation_for_magnitude(parse_magnitude(mag))
    return None


def quantity_table(title: str) -> Table:
    """A rich table with the 'quantity' and right-aligned 'value' columns of the results."""
    t = Table(title=title, title_justify="left")
    t.add_column("quantity")
    t.add_column("value", justify="right")
    return t
