"""Optical gain and delay of the probed mode from the OGTL probe (a sine added to the mode's
commands).  On Tip/Tilt the plant carries the structural resonance, z^-d (1 + G), divided out.

With the probe added after the controller, c is what the mirror is given and the mirror
holds z^-d c, so at the probe frequency the measurement and the commands are related by the
plant alone, whatever the controller and the disturbance:

    M / C = -chi z^-d  at z = exp(j 2 pi f_p / rate)        (m/k = chi (phi - mirror) + n)

(the closed loop's sensitivity cancels between the two).  |M/C| gives chi (divided by the
delay line's |z^-d|, below 1 for a fractional delay), the phase gives d modulo the probe's
period in frames (rate / f_p: 4 frames at the default quarter of the frame rate), resolved
with the rejection fit's delay.  M and C are lock-in amplitudes over the window; their
uncertainty is the lock-in's own, from the same demodulation at off-probe frequencies
(``control.ogtl.REFERENCE_BINS``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from ..control.ogtl import REFERENCE_BINS, demodulate
from .plant import Estimate
from .record import LoopRecord, plant_response


@dataclass(frozen=True)
class ProbeFit:
    mode: int  # 1-based
    frequency_hz: float
    chi: Estimate  # k divided out
    delay: Estimate


def _delay_from_phase(response: Callable[[float], complex], phase: float, w: float, near: float) -> float:
    """The d >= 0 closest to ``near`` whose plant ``response(d)`` has the phase ``phase`` (w: the
    probe's rad/frame, whose period in frames bounds the search)."""

    def off(d: float) -> float:
        return float(np.angle(np.exp(1j * (np.angle(response(d)) - phase))))

    period = 2 * np.pi / w
    grid = np.arange(max(0.0, near - period), near + period, period / 400.0)
    diff = np.array([off(d) for d in grid])
    roots = [brentq(off, a, b) for a, b, da, db in zip(grid, grid[1:], diff, diff[1:]) if da * db < 0 and abs(da - db) < np.pi]
    return min(roots, key=lambda d: abs(d - near)) if roots else math.nan


def fit_probe(record: LoopRecord, near_delay: float) -> ProbeFit | None:
    """chi and d of the probed mode (see the module); None without a probe."""
    if record.probe is None or record.probe_series is None:
        return None
    m, c = record.probe_series
    f, rate, first = record.probe.frequency_hz, record.rate_hz, record.first_frame
    M, C = demodulate(m, f, rate, first), demodulate(c, f, rate, first)
    step = rate / len(m)
    reference = [demodulate(m, f + j * step, rate, first) for j in REFERENCE_BINS if 0 < f + j * step < rate / 2]
    sigma_m = float(np.sqrt(np.mean(np.abs(reference) ** 2) / 2.0)) if reference else math.inf
    if not abs(C) > 0:
        return None
    w = 2 * np.pi * f / rate
    ratio = -M / C  # chi times the plant's response: z^-d, and 1 + G on Tip/Tilt

    tip_tilt = record.probe.mode <= 2

    def response(d: float) -> complex:
        return complex(plant_response(record, d, tip_tilt, [f])[0])

    d = _delay_from_phase(response, float(np.angle(ratio)), w, near_delay)
    gain = abs(response(d)) if math.isfinite(d) else 1.0
    rel = sigma_m / abs(M) if abs(M) > 0 else math.inf
    chi = abs(ratio) / gain
    return ProbeFit(record.probe.mode, f, Estimate(chi, chi * rel), Estimate(d, rel / w))
