"""Trial-and-error gain optimisation, as FLAO has run it since 2010 (paper Sec. MGM): three gain
groups - Tip/Tilt, modes 3-120, modes 121-last - each scanned over a range of gains in short
closed-loop sequences, in that order; the gain of least merit is kept for the rest of the run.

Merit: the RMS of the group's measured modes R s (the slopes projected on the group's modes)
over the sequence.  The paper uses the RMS of all slopes; in a linear loop both are minimal at
the same gain of the scanned group (the slopes' other modes do not depend on it), but the
projection leaves out the other groups' fluctuations and so scatters less between sequences.
Each gain is scored twice, on the way up the scan and on the way down, and its merit is the
mean of the two (``scan_order``): a drift of the turbulence over the scan then cannot pass for
a trend with the gain.  The minimum is taken from a parabola through the best sample and its two neighbours (not just
the best sample), kept within those neighbours; at the ends of the scan, or where the three
points are not convex, the best sample.  A scan around an operating point keeps the gain it
started from unless another is better by more than the merit's own scatter (``chosen_gain``),
both judged on the scan smoothed by a running median of three, so that one sequence's
fluctuation cannot decide alone.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError

SIGNIFICANCE = 2.0  # a scanned gain replaces the incumbent when better by this many merit scatters
SCAN_PASSES = 2  # each gain is scored on the way up and on the way down (``scan_order``)


def scan_gains(upper: float, n_values: int = 8, lowest_fraction: float = 0.05) -> np.ndarray:
    """``n_values`` gains evenly spaced from ``lowest_fraction`` x upper to upper."""
    if not (upper > 0 and np.isfinite(upper)):
        raise InputError(f"the top of a gain scan must be a finite number > 0, got {upper}")
    if n_values < 3:
        raise InputError(f"a gain scan needs at least 3 values, got {n_values}")
    return np.linspace(lowest_fraction * upper, upper, n_values)


def scan_around(centre: float, upper: float, span: float = 3.0, n_values: int = 8) -> np.ndarray:
    """``n_values`` gains spaced geometrically from ``centre / span`` to ``min(span x centre,
    upper)``, and ``centre`` itself (when not above ``upper``): a scan around an operating
    point.  A scan from near zero puts its first, lowest gain into a loop whose residual has not
    yet grown to that gain's level and whose pyramid saturates on the large Tip/Tilt
    excursions, so that the slope RMS under-reports exactly the worst gain (docs/physics.md)."""
    if not (centre > 0 and np.isfinite(centre)):
        raise InputError(f"the centre of a gain scan must be a finite number > 0, got {centre}")
    if not (upper > 0 and np.isfinite(upper)) or not span > 1:
        raise InputError(f"a gain scan needs a finite upper gain > 0 and a span > 1, got {upper}, {span}")
    lo, hi = min(centre / span, upper / span), min(span * centre, upper)
    scan = np.geomspace(lo, hi, n_values)
    return np.unique(np.append(scan, centre)) if centre <= upper else scan


def scan_order(n_values: int, passes: int = SCAN_PASSES) -> np.ndarray:
    """The order in which a scan's gains (indices into the ascending scan) are visited: up,
    then down, and so on for ``passes``.  Each gain's merit is the mean of its visits
    (``merits_by_gain``), so that a drift of the turbulence over the scan, linear in time,
    adds the same to every gain instead of passing for a trend with the gain: at R14.5, 1.0",
    seed 3 the Tip/Tilt merits fell from 90 to 74 up a single pass and its top gain, 0.96,
    was kept (Strehl -0.024); scanned downwards on the same turbulence, that gain scored 79
    and the incumbent was kept."""
    if n_values < 1 or passes < 1:
        raise InputError(f"a scan order needs at least one value and one pass, got {n_values}, {passes}")
    up = np.arange(n_values)
    return np.concatenate([up if p % 2 == 0 else up[::-1] for p in range(passes)])


def merits_by_gain(visits, merits, n_values: int) -> np.ndarray:
    """Per gain of the scan (index 0..n_values-1), the mean merit of its ``visits`` (indices,
    with their ``merits``); infinite where a visit failed (infinite) or the gain was never
    scored."""
    out = np.full(n_values, math.inf)
    v, m = np.asarray(visits, dtype=int), np.asarray(merits, dtype=float)
    for i in range(n_values):
        mine = m[v == i]
        if mine.size and np.all(np.isfinite(mine)):
            out[i] = float(np.mean(mine))
    return out


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


def merit_scatter(merits) -> float:
    """The sequence-to-sequence scatter of a scan's merits: the standard deviation of the
    differences of neighbouring sequences (von Neumann's estimator: a smooth trend over the
    scan cancels in the differences, the turbulence's and the noise's fluctuation from one
    short sequence to the next does not), over the finite merits; 0 with fewer than 3."""
    m = np.asarray(merits, dtype=float)
    m = m[np.isfinite(m)]
    return float(np.std(np.diff(m), ddof=1)) if m.size >= 3 else 0.0


def running_median(merits) -> np.ndarray:
    """The scan's merits (in gain order) smoothed by a running median of three (Tukey); the
    two ends keep their own.  A failed gain's infinite merit counts as the worst."""
    m = np.asarray(merits, dtype=float)
    out = m.copy()
    if m.size >= 3:
        out[1:-1] = np.median(np.stack([m[:-2], m[1:-1], m[2:]]), axis=0)
    return out


def chosen_gain(gains, merits, incumbent: float | None = None) -> float:
    """``best_gain``, but the ``incumbent`` (a gain of the scan: the one the loop ran at)
    when the best merit beats the incumbent's by no more than SIGNIFICANCE x ``merit_scatter``,
    both merits read from the scan smoothed by ``running_median``.  Why: with 0.2 s sequences
    the merit of a Tip/Tilt scan at R14.5, 1.0" scattered by +-10 % with no trend, and its
    minimum, a fluctuation, moved the gain from 0.51 to 0.28 (hence the scatter); at seed 2
    the incumbent's own sequence drew a merit 12 % above both its neighbours, and the
    unsmoothed comparison moved the gain to 0.75, which lost 0.014 in Strehl (hence the
    median).  On trendless scans of 9 gains with Gaussian noise the incumbent is replaced 3 %
    of the time, against 10 % unsmoothed."""
    best = best_gain(gains, merits)
    if incumbent is None:
        return best
    g, m = np.asarray(gains, dtype=float), np.asarray(merits, dtype=float)
    at = np.flatnonzero(np.isclose(g, incumbent, rtol=1e-9, atol=0.0))
    if at.size == 0 or not np.isfinite(m[at[0]]):
        return best
    order = np.argsort(g, kind="stable")
    smooth = np.empty_like(m)
    smooth[order] = running_median(m[order])
    gain_over_incumbent = smooth[at[0]] - np.min(np.where(np.isfinite(smooth), smooth, np.inf))
    return float(incumbent) if gain_over_incumbent <= SIGNIFICANCE * merit_scatter(m) else best
