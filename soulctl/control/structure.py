"""The 127 Hz control-structure interaction of the adaptive secondary (paper, Sec. on the
Tip/Tilt IIR: an integrator at high gain excites a 127 Hz vibration).

Model: a lightly damped Tip/Tilt mode of the structure that carries the ASM, driven by the
reaction of the mirror's own Tip/Tilt motion (the force that accelerates the shell pushes the
structure back), so that its wavefront Tip/Tilt is

    y(s) = G(s) u(s),   G(s) = kappa s^2 / (s^2 + 2 zeta w0 s + w0^2),

u the mirror's Tip/Tilt command: zero at low frequency, kappa / (2 zeta) at f0 (with a +90 deg
phase), kappa above.  The plant the loop sees becomes z^-d (1 + G(z)).  Defaults: f0 = 127 Hz
(paper), damping 0.05 (domain notes), coupling kappa = 0.2 (a proposal: with it the 1700 Hz
integrator's maximum stable gain drops from 0.52 to 0.34 and |S| peaks at 12 near 127 Hz at
g = 0.3, while the paper's 1700 Hz IIR at g = 0.69 keeps a peak |S| of 1.7).  Discretised by
the bilinear transform prewarped at f0, so the peak stays at f0 at any frame rate.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError


@dataclass(frozen=True)
class StructuralResonance:
    frequency_hz: float = 127.0
    damping: float = 0.05
    coupling: float = 0.2

    def __post_init__(self):
        if not (0 < self.frequency_hz < 1e5):
            raise InputError(f"resonance frequency must be in 0..1e5 Hz, got {self.frequency_hz:g}")
        if not (0 < self.damping < 1):
            raise InputError(f"resonance damping must be in 0..1 (exclusive), got {self.damping:g}")
        if not (0 <= self.coupling <= 10):
            raise InputError(f"resonance coupling must be in 0..10, got {self.coupling:g}")

    def coefficients(self, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
        """(b, a) of G(z) in powers of z^-1 at ``rate_hz``."""
        if not (rate_hz > 2 * self.frequency_hz):
            raise InputError(f"a {self.frequency_hz:g} Hz resonance needs a frame rate above {2 * self.frequency_hz:g} Hz, got {rate_hz:g}")
        w0 = 2 * math.pi * self.frequency_hz
        prewarped = w0 / (2 * math.tan(w0 / (2 * rate_hz)))  # the 'fs' that maps w0 exactly
        if self.coupling == 0:
            return np.zeros(3), np.array([1.0, 0.0, 0.0])
        from scipy.signal import bilinear  # here, not at the top: the CLI starts without scipy.signal

        b, a = bilinear([self.coupling, 0.0, 0.0], [1.0, 2 * self.damping * w0, w0**2], fs=prewarped)
        return np.asarray(b, float), np.asarray(a, float)

    def frequency_response(self, f_hz, rate_hz: float) -> np.ndarray:
        b, a = self.coefficients(rate_hz)
        zi = np.exp(-2j * np.pi * np.asarray(f_hz, dtype=float) / rate_hz)
        return np.polyval(b[::-1], zi) / np.polyval(a[::-1], zi)


def sampled_structure(structure: StructuralResonance | None, rate_hz: float) -> StructuralResonance | None:
    """The structural resonance if the loop samples it (f0 below Nyquist), else None: a loop at
    250 Hz does not see a 127 Hz mode (its detector and hold filter it; not modelled)."""
    return structure if structure is not None and structure.frequency_hz < rate_hz / 2 else None


def sampled_coefficients(structure: StructuralResonance | None, rate_hz: float) -> tuple | None:
    """The (b, a) of G(z), as tuples, of the resonance the rate samples (``sampled_structure``);
    None without one: what the loop models (``transfer.Plant``, ``mgm``) take."""
    sampled = sampled_structure(structure, rate_hz)
    return None if sampled is None else tuple(tuple(map(float, x)) for x in sampled.coefficients(rate_hz))
