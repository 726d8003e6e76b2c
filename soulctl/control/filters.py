"""Control filters as data: zeros, poles and gain, and their RTC state-space realisation.

A filter is (paper, Eq. tfIIR, written in z^-1 as its state space is)

    H(z) = g * prod_k (1 - beta_k z^-1) / prod_l (1 - alpha_l z^-1).

For equal numbers of zeros and poles (the Tip/Tilt IIR filters) this is the paper's
g prod(z - beta) / prod(z - alpha).  For the leaky integrator (no zero, one pole) the paper's
state space A = alpha, B = g, C = 1 gives g / (1 - alpha z^-1) = g z / (z - alpha): the z-form
of Eq. tfIIR lacks that factor z, and soulctl follows the state space, as the RTC does.

State-space realisation (paper, Eq. stateIIR, with null feed-forward matrix): with
N_alpha poles and N_beta zeros the state holds the N_alpha latest outputs and the N_beta latest
inputs scaled by the gain,

    x(k) = [y(k), ..., y(k-N_alpha+1), g u(k), ..., g u(k-N_beta+1)],

so that A does not depend on g and B = G(g) B_unit with G(g) = g I: only the RTC's Delta
carries the gain, and it may change between two steps.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputError


def _real_poly(roots: tuple[complex, ...], what: str) -> np.ndarray:
    """Coefficients of prod(1 - r z^-1) in powers of z^-1; roots must be real or conjugate pairs."""
    c = np.poly(np.asarray(roots, dtype=complex)) if roots else np.array([1.0 + 0j])
    if np.max(np.abs(c.imag)) > 1e-9:
        raise InputError(f"{what} must be real or come in complex-conjugate pairs, got {list(roots)}")
    return c.real


@dataclass(frozen=True)
class Filter:
    zeros: tuple[complex, ...]
    poles: tuple[complex, ...]
    gain: float

    def __post_init__(self):
        if len(self.poles) < 1:
            raise InputError("a control filter needs at least one pole (the RTC realises IIR filters)")
        if not np.isfinite(self.gain):
            raise InputError(f"filter gain must be finite, got {self.gain}")
        # Validates the conjugate-pair condition early.
        _real_poly(self.zeros, "zeros")
        _real_poly(self.poles, "poles")

    @classmethod
    def integrator(cls, gain: float) -> "Filter":
        """Pure integrator g / (1 - z^-1)."""
        return cls((), (1.0,), float(gain))

    @classmethod
    def leaky(cls, forgetting: float, gain: float) -> "Filter":
        """Leaky integrator g / (1 - alpha z^-1), alpha the forgetting factor (paper, Eq. stateINT)."""
        if not 0.0 <= forgetting <= 1.0:
            raise InputError(f"forgetting factor must be in [0, 1], got {forgetting:g}")
        return cls((), (float(forgetting),), float(gain))

    @classmethod
    def iir(cls, zeros, poles, gain: float) -> "Filter":
        """General IIR filter from its zeros, poles and gain."""
        return cls(tuple(zeros), tuple(poles), float(gain))

    def with_gain(self, gain: float) -> "Filter":
        return replace(self, gain=float(gain))

    @property
    def n_states(self) -> int:
        """N_f = N_alpha + N_beta, the RTC states this filter takes."""
        return len(self.zeros) + len(self.poles)

    def coefficients(self) -> tuple[np.ndarray, np.ndarray]:
        """(b, a) in powers of z^-1, gain included in b: H = (b0 + b1 z^-1 + ...)/(1 + a1 z^-1 + ...)."""
        return self.gain * _real_poly(self.zeros, "zeros"), _real_poly(self.poles, "poles")

    def unit_state_space(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A, B_unit, C) of the realisation above: x(k) = A x(k-1) + g B_unit u(k), y(k) = C x(k)."""
        b = _real_poly(self.zeros, "zeros")  # monic: b[0] = 1
        a = _real_poly(self.poles, "poles")
        na, nb = len(self.poles), len(self.zeros)
        n = na + nb
        A = np.zeros((n, n))
        A[0, :na] = -a[1:]
        A[0, na:] = b[1:]
        for k in range(1, na):  # y(k-k) <- y(k-k+1)
            A[k, k - 1] = 1.0
        for k in range(1, nb):  # g u(k-k) <- g u(k-k+1)
            A[na + k, na + k - 1] = 1.0
        B = np.zeros(n)
        B[0] = b[0]
        if nb:
            B[na] = 1.0
        C = np.zeros(n)
        C[0] = 1.0
        return A, B, C
