"""A sweep grid: a TOML file whose keys are `loop run` parameters, each a value or a list (an
axis of the grid).  The cases are the Cartesian product of the lists, in the file's order.

    # Strehl versus magnitude at two seeings, 10x10 sub-apertures
    magnitude = [15.0, 16.0, 17.0]
    seeing = [0.8, 1.2]
    binning = 4
    duration = 0.5
    seed = 1

Parameters (defaults as `loop run`): magnitude (R), seeing (arcsec), wind (m/s), L0 (m),
duration (s), binning (1-4; with it the look-up table's sub-apertures and modes for that
binning), frame_rate (Hz; the Tip/Tilt IIR of the nearest tabulated rate, an integrator below
750 Hz), tt_control (iir|int), gain_method (default|mgm|trial), band, seed, noise (bool),
vibrations (bool), resonance (bool), oversampling (1-4).  gain_method = "mgm": MGM with OGTL
for ``duration`` (an update every half of it, at most 1 s), then the metrics over another
``duration``; "trial": the three-group scan (0.25 s per gain), then the same.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
from pathlib import Path

from ..errors import InputError
from ..files import read_toml
from ..loop.metrics import BANDS

PARAMETERS = {
    # name: (accepted types, check, accepted range text)
    "magnitude": ((int, float), lambda v: 0 <= v <= 18.5, "0..18.5"),
    "seeing": ((int, float), lambda v: 0.05 <= v <= 10, "0.05..10 arcsec"),
    "wind": ((int, float), lambda v: 0 <= v <= 100, "0..100 m/s"),
    "L0": ((int, float), lambda v: 0 < v <= 1e4, "0..10000 m (> 0)"),
    "duration": ((int, float), lambda v: 0 < v <= 600, "0..600 s (> 0)"),
    "binning": ((int,), lambda v: v in (1, 2, 3, 4), "1, 2, 3 or 4"),
    "frame_rate": ((int, float), lambda v: 10 <= v <= 2000, "10..2000 Hz"),
    "tt_control": ((str,), lambda v: v in ("iir", "int"), "iir or int"),
    "gain_method": ((str,), lambda v: v in ("default", "mgm", "trial"), "default, mgm or trial"),
    "band": ((str,), lambda v: v in BANDS, ", ".join(BANDS)),
    "seed": ((int,), lambda v: 0 <= v < 2**63, "0..2^63-1"),
    "noise": ((bool,), lambda v: True, "true or false"),
    "vibrations": ((bool,), lambda v: True, "true or false"),
    "resonance": ((bool,), lambda v: True, "true or false"),
    "oversampling": ((int,), lambda v: v in (1, 2, 3, 4), "1..4"),
}
REQUIRED = ("magnitude",)
MAX_CASES = 100_000


def _check(name: str, value, where: str):
    types, ok, accepted = PARAMETERS[name]
    if isinstance(value, bool) and bool not in types:
        raise InputError(f"{where}: {name} must be {accepted}, got {value!r}")
    if not isinstance(value, types) or (isinstance(value, float) and not math.isfinite(value)) or not ok(value):
        raise InputError(f"{where}: {name} must be {accepted}, got {value!r}")
    return float(value) if float in types and not isinstance(value, bool) else value


def parse_grid(data: dict, where: str = "grid") -> list[dict]:
    """The cases of a grid (a dict as read from TOML); InputError for an unknown parameter, a
    value out of its range, an empty list or a grid without cases."""
    if not data:
        raise InputError(f"{where} is empty: give at least 'magnitude = [...]'")
    unknown = sorted(set(data) - set(PARAMETERS))
    if unknown:
        raise InputError(f"{where}: unknown parameter {', '.join(unknown)}; accepted: {', '.join(PARAMETERS)}")
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
