"""Trial-and-error gain optimisation, as FLAO has run it since 2010 (paper Sec. MGM): three gain
groups - Tip/Tilt, modes 3-120, modes 121-last - each scanned over a range of gains in short
closed-loop sequences, in that order; the gain of least merit is kept for the rest of the run.

Merit: the RMS of the group's measured modes R s (the slopes projected on the group's modes)
over the sequence.  The paper uses the RMS of all slopes; in a linear loop both are minimal at
the same gain of the scanned group (the slopes' other modes do not depend on it), but the
projection leaves out the other groups' fluctuations and so scatters less between sequences.
The minimum is taken from a parabola through the best sample and its two neighbours (not just
the best sample), kept within those neighbours; at the ends of the scan, or where the three
points are not convex, the best sample.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError

MID_GROUP_END = 120  # modes 3-120 (1-based) are the middle group


def gain_groups(n_modes: int) -> list[tuple[str, slice]]:
    """The paper's three groups (0-based slices), without the empty ones."""
    groups = [("tip-tilt", slice(0, min(2, n_modes))), ("modes 3-120", slice(2, min(MID_GROUP_END, n_modes))),
              (f"modes 121-{n_modes}", slice(MID_GROUP_END, n_modes))]
    return [(name, s) for name, s in groups if s.stop > s.start]


def scan_gains(upper: float, n_values: int = 8, lowest_fraction: float = 0.05) -> np.ndarray:
    """``n_values`` gains evenly spaced from ``lowest_fraction`` x upper to upper."""
    if not (upper > 0 and np.isfinite(upper)):
        raise InputError(f"the top of a gain scan must be a finite number > 0, got {upper}")
    if n_values < 3:
        raise InputError(f"a gain scan needs at least 3 values, got {n_values}")
    return np.linspace(lowest_fraction * upper, upper, n_values)


def best_gain(gains, merits) -> float:
    """The gain of least merit from a scan (see the module docstring)."""
    g = np.asarray(gains, dtype=float)
    m = np.asarray(merits, dtype=float)
    if g.shape != m.shape or g.size < 3:
        raise InputError("best_gain needs at least 3 (gain, merit) pairs of the same length")
    finite = np.isfinite(m)
    if not finite.any():
        raise InputError("no finite merit in the gain scan")
    m = np.where(finite, m, np.inf)
    j = int(np.argmin(m))
    if j == 0 or j == g.size - 1 or not np.all(np.isfinite(m[j - 1 : j + 2])):
        return float(g[j])
    a, b, _ = np.polyfit(g[j - 1 : j + 2], m[j - 1 : j + 2], 2)
    if a <= 0:
        return float(g[j])
    return float(np.clip(-b / (2 * a), g[j - 1], g[j + 1]))
