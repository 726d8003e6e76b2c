"""A whole RTC description as a file: Lambda, Delta (its diagonal, or the matrix), Xi, Sigma
and, optionally, R (modes x slopes) and M (commands x modes), the arrays the C++ core takes
(``rtc.build_rtc``).  Formats by suffix: ``.npz`` (numpy), ``.h5``/``.hdf5`` (datasets at the
root), ``.fits`` (image HDUs named LAMBDA, DELTA, XI, SIGMA, R, M).

``compare`` rebuilds the matrices from the declared filters (the configuration's Tip/Tilt
filter and leaky integrators, the gains read from Delta) and R, M, and reports the largest
difference of each matrix: a description whose Lambda does not hold the declared filters'
poles, or whose Xi / Sigma are not B R / M C, is caught before an upload.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import input_file
from .filters import Filter
from .gains import mode_gains
from .rtc import build_rtc

NAMES = ("Lambda", "Delta", "Xi", "Sigma", "R", "M")
REQUIRED = NAMES[:4]
SUFFIXES = (".npz", ".h5", ".hdf5", ".fits")
TOLERANCE = 1e-6  # relative to each matrix's largest element


def is_rtc_file(path: str | Path) -> bool:
    return Path(path).suffix.lower() in SUFFIXES


def read_rtc_file(path: str | Path) -> dict[str, np.ndarray]:
    """The arrays of an RTC description (InputError naming a missing, non-finite or misshaped one)."""
    p = input_file(path, "RTC description")
    suffix = p.suffix.lower()
    try:
        if suffix == ".npz":
            with np.load(p, allow_pickle=False) as z:
                arrays = {k: np.asarray(z[k], dtype=float) for k in NAMES if k in z.files}
        elif suffix == ".fits":
            from astropy.io import fits

            with fits.open(p) as hdul:
                arrays = {k: np.asarray(hdul[k.upper()].data, dtype=float) for k in NAMES if k.upper() in hdul}
        else:
            import h5py

            with h5py.File(p, "r") as f:
                arrays = {k: np.asarray(f[k], dtype=float) for k in NAMES if isinstance(f.get(k), h5py.Dataset)}
    except (OSError, ValueError, TypeError, KeyError) as e:
        raise InputError(f"RTC description {path}: cannot read it ({' '.join(str(e).split())})") from None
    missing = [k for k in REQUIRED if k not in arrays]
    if missing:
        raise InputError(f"RTC description {path}: missing {', '.join(missing)} (needs {', '.join(REQUIRED)}; R and M optional)")
    for k, a in arrays.items():
        if not np.all(np.isfinite(a)):
            raise InputError(f"RTC description {path}: {k} holds NaN or infinite values")
    _check_shapes(arrays, path)
    if arrays["Delta"].ndim == 2:
        arrays["Delta"] = np.diag(arrays["Delta"]).copy()
    return arrays


def _check_shapes(a: dict, path) -> None:
    n = a["Lambda"].shape[0]
    rules = [
        ("Lambda", a["Lambda"].shape == (n, n), f"({n}, {n})"),
        ("Delta", a["Delta"].shape in ((n,), (n, n)), f"({n},) or ({n}, {n})"),
        ("Xi", a["Xi"].ndim == 2 and a["Xi"].shape[0] == n, f"({n}, n_slopes)"),
        ("Sigma", a["Sigma"].ndim == 2 and a["Sigma"].shape[1] == n, f"(n_commands, {n})"),
    ]
    if "R" in a:
        rules.append(("R", a["R"].ndim == 2 and a["R"].shape[1] == a["Xi"].shape[1], f"(n_modes, {a['Xi'].shape[1]})"))
    if "M" in a:
        rules.append(("M", a["M"].ndim == 2 and a["M"].shape[0] == a["Sigma"].shape[0], f"({a['Sigma'].shape[0]}, n_modes)"))
    for name, ok, expected in rules:
        if not ok:
            raise InputError(f"RTC description {path}: {name} has shape {a[name].shape}, expected {expected}")


@dataclass(frozen=True)
class Comparison:
    gains: np.ndarray  # per mode, from Delta
    differences: dict  # matrix -> largest |difference| / largest |element| (None: not compared)

    @property
    def consistent(self) -> bool:
        return all(d is None or d <= TOLERANCE for d in self.differences.values())


def compare(arrays: dict, unit_filters: list[Filter]) -> Comparison:
    """Rebuild with the declared filters at the gains Delta holds and compare (see the module)."""
    n_states = arrays["Lambda"].shape[0]
    n_modes = len(unit_filters)
    R = arrays.get("R", np.zeros((n_modes, arrays["Xi"].shape[1])))
    M = arrays.get("M", np.zeros((arrays["Sigma"].shape[0], n_modes)))
    if R.shape[0] != n_modes or M.shape[1] != n_modes:
        raise InputError(f"RTC description: R and M hold {R.shape[0]} and {M.shape[1]} modes; the configuration controls {n_modes}")
    layout = build_rtc(unit_filters, R, M, n_states)
    gains = mode_gains(layout.blocks, n_modes, arrays["Delta"])
    rebuilt = build_rtc([h.with_gain(g) for h, g in zip(unit_filters, gains)], R, M, n_states)
    diffs: dict[str, float | None] = {}
    for name, mine in (("Lambda", rebuilt.Lambda), ("Delta", rebuilt.Delta), ("Xi", rebuilt.Xi), ("Sigma", rebuilt.Sigma)):
        if name in ("Xi", "Sigma") and not {"R", "M"} <= set(arrays):
            diffs[name] = None
            continue
        theirs = arrays[name]
        scale = max(float(np.max(np.abs(theirs))), float(np.max(np.abs(mine))), 1e-300)
        diffs[name] = float(np.max(np.abs(theirs - mine))) / scale
    return Comparison(gains, diffs)
