"""A sweep grid: a TOML file whose keys are `loop run` parameters, each a value or a list (an
axis of the grid).  The cases are the Cartesian product of the lists, in the file's order.

    # Strehl versus magnitude at two seeings, 10x10 sub-apertures
    magnitude = [15.0, 16.0, 17.0]
    seeing = [0.8, 1.2]
    binning = 4
    duration = 0.5
    seed = 1

Parameters (defaults as `loop run`; the ranges are soulctl.ranges', the ones `loop run`
accepts): magnitude (R, the look-up table's range), seeing (arcsec), wind (m/s, > 0), L0 (m),
duration (s), binning (1-4; with it the look-up table's sub-apertures and modes for that
binning), frame_rate (Hz; the Tip/Tilt IIR of the nearest tabulated rate, an integrator below
750 Hz), tt_control (iir|int), gain_method (default|mgm|trial), band, seed, noise (bool),
vibrations (bool), resonance (bool), oversampling (1-4), wfs_field (arcsec, 0-4; SOUL's 2.1 by
default, 0: the sampled field without a stop).  Any other field of the run
description (``soulctl.run_config``) is a parameter by its dotted name, e.g.
``"atmosphere.L0_m" = [20.0, 40.0]`` or ``"control.forgetting" = 1.0`` (a number, integer,
boolean or text; checked as the run description checks it).  gain_method = "mgm": MGM with OGTL
for ``duration`` (an update every half of it, at most 1 s), then the metrics over another
``duration``; "trial": the three-group scan (0.25 s per gain), then the same.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
from dataclasses import dataclass
from pathlib import Path

from .. import ranges, tables
from ..errors import InputError
from ..files import read_toml
from ..loop.metrics import BANDS
from ..observation import BINNINGS
from ..ranges import Range
from ..run_config import KEYS, RunConfig


@dataclass(frozen=True)
class Parameter:
    """A grid parameter: its type (float, int, bool or str) and either its range (the one of
    ``soulctl.ranges``, shared with `loop run`) or its accepted values."""

    kind: type
    range: Range | None = None
    choices: tuple = ()

    def text(self) -> str:
        """The accepted values as messages show them."""
        if self.range is not None:
            return self.range.text()
        if self.kind is bool:
            return "true or false"
        words = [str(c) for c in self.choices]
        return words[0] if len(words) == 1 else ", ".join(words[:-1]) + " or " + words[-1]

    def check(self, value, name: str):
        """``value`` as the case holds it (ints of float parameters become floats), else an
        InputError naming ``name`` and the accepted values."""
        if self.range is not None:
            return self.range.check(value, name)  # refuses bools, NaN, infinities and non-numbers
        if self.kind is bool:
            ok = isinstance(value, bool)
        else:
            ok = type(value) is self.kind and value in self.choices
        if not ok:
            raise InputError(f"{name} must be {self.text()}, got {value!r}")
        return value


PARAMETERS = {
    "magnitude": Parameter(float, Range(*tables.magnitude_range(tables.magnitude_table()))),  # the look-up table's
    "seeing": Parameter(float, ranges.SEEING_ARCSEC),
    "wind": Parameter(float, ranges.WIND_M_S),
    "L0": Parameter(float, ranges.OUTER_SCALE_M),
    "duration": Parameter(float, ranges.DURATION_S),
    "binning": Parameter(int, choices=tuple(BINNINGS)),
    "frame_rate": Parameter(float, ranges.FRAME_RATE_HZ),
    "tt_control": Parameter(str, choices=("iir", "int")),
    "gain_method": Parameter(str, choices=("default", "mgm", "trial")),
    "band": Parameter(str, choices=tuple(BANDS)),
    "seed": Parameter(int, ranges.SEED),
    "noise": Parameter(bool),
    "vibrations": Parameter(bool),
    "resonance": Parameter(bool),
    "oversampling": Parameter(int, ranges.OVERSAMPLING),
    "wfs_field": Parameter(float, ranges.WFS_FIELD_OF_VIEW_ARCSEC),
}
REQUIRED = ("magnitude",)
# The parameters as fields of the run description (gain_method is the sweep's own).
FIELDS = {
    "magnitude": "star.magnitude_r",
    "binning": "wfs.binning",
    "frame_rate": "wfs.frame_rate_hz",
    "tt_control": "control.tt_control",
    "seeing": "atmosphere.seeing_arcsec",
    "wind": "atmosphere.wind_m_s",
    "L0": "atmosphere.L0_m",
    "duration": "run.duration_s",
    "band": "run.band",
    "seed": "run.seed",
    "oversampling": "run.oversampling",
    "wfs_field": "run.wfs_field_arcsec",
    "noise": "detector.noise",
    "vibrations": "vibrations.enabled",
    "resonance": "structure.enabled",
}
MAX_CASES = 100_000


def _check(name: str, value, where: str):
    try:
        if name in PARAMETERS:
            return PARAMETERS[name].check(value, name)
        return _check_field(name, value)
    except InputError as e:
        raise InputError(f"{where}: {e}") from None


def is_field(name: str) -> bool:
    """A run description field given by its dotted name (a scalar one: not the layer or line tables)."""
    section, _, key = name.partition(".")
    return key in (KEYS.get(section) or ()) and key not in ("layer", "line")


def _check_field(name: str, value):
    """A dotted field's value, checked by the run description it makes of the defaults."""
    if isinstance(value, (dict, list)) or not isinstance(value, (bool, int, float, str)):
        raise InputError(f"{name} must be a number, an integer, true or false, or text, got {value!r}")
    RunConfig().with_values({name: value})
    return value


def parse_grid(data: dict, where: str = "grid") -> list[dict]:
    """The cases of a grid (a dict as read from TOML); InputError for an unknown parameter, a
    value out of its range, an empty list or a grid without cases."""
    if not data:
        raise InputError(f"{where} is empty: give at least 'magnitude = [...]'")
    unknown = sorted(name for name in data if name not in PARAMETERS and not is_field(name))
    if unknown:
        raise InputError(
            f"{where}: unknown parameter {', '.join(unknown)}; accepted: {', '.join(PARAMETERS)} or a run description field by "
            "its dotted name (e.g. atmosphere.L0_m)"
        )
    twice = sorted(name for name in data if FIELDS.get(name) in data)
    if twice:
        raise InputError(f"{where}: {twice[0]} and {FIELDS[twice[0]]} are the same parameter: give one")
    short = {f: name for name, f in FIELDS.items()}
    data = {short.get(name, name): value for name, value in data.items()}  # one name per parameter
    missing = [k for k in REQUIRED if k not in data]
    if missing:
        raise InputError(f"{where}: needs {', '.join(missing)}")
    axes = []
    for name, value in data.items():
        values = value if isinstance(value, list) else [value]
        if not values:
            raise InputError(f"{where}: {name} is an empty list (the grid would have no case)")
        axes.append([(name, _check(name, v, where)) for v in values])
    n = math.prod(len(a) for a in axes)
    if n > MAX_CASES:
        raise InputError(f"{where}: {n} cases, more than {MAX_CASES}")
    return [dict(case) for case in itertools.product(*axes)]


def read_grid(path: str | Path) -> list[dict]:
    return parse_grid(read_toml(Path(path), "grid file"), f"grid file {path}")


def case_id(case: dict) -> str:
    """A short stable identifier of a case (its parameters, sorted): rows are resumed by it."""
    text = json.dumps(case, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]
