"""Control filters as data: zeros, poles and gain, and their RTC state-space realisation.

A filter is (paper, Eq. tfIIR, written in z^-1 as its state space is)

    H(z) = g * prod_k (1 - beta_k z^-1) / prod_l (1 - alpha_l z^-1).

For equal numbers of zeros and poles (the Tip/Tilt IIR filters) this is the paper's
g prod(z - beta) / prod(z - alpha).  For the leaky integrator (no zero, one pole) the paper's
state space A = alpha, B = g, C = 1 gives g / (1 - alpha z^-1) = g z / (z - alpha): the z-form
of Eq. tfIIR lacks that factor z, and soulctl follows the state space, as the RTC does.

State-space realisation (paper, Eq. stateIIR, with null feed-forward matrix), N_f = N_alpha +
N_beta states, A independent of g and B = G(g) B_unit with G(g) = g I, so that only the RTC's
Delta carries the gain and it may change between two steps:

* no pole at z = 1: direct form, the N_alpha latest outputs and N_beta latest inputs scaled by
  the gain, x(k) = [y(k), ..., y(k-N_alpha+1), g u(k), ..., g u(k-N_beta+1)] (the paper's "N_f/2
  past values of u and y");
* a pole at z = 1 (integral action, all Tip/Tilt filters of the paper): the integrator is kept
  as its own state, y(k) = y(k-1) + w(k), with w the direct form of the other poles,
  x(k) = [w(k), ..., w(k-N_alpha+2), g u(k), ..., g u(k-N_beta+1), y(k)].  Its 1.0 in Lambda is
  exact in float32; in a float32 direct form the rounded coefficients move that pole, to
  1 + 3.8e-6 for the paper's 1350 Hz filter (a slow divergence of the integrator).
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
        if not all(np.isfinite(complex(r)) for r in (*self.zeros, *self.poles)):
            raise InputError(f"filter zeros and poles must be finite, got {list(self.zeros)} and {list(self.poles)}")
        # Validates the conjugate-pair condition early.
        _real_poly(self.zeros, "zeros")
        _real_poly(self.poles, "poles")

    @classmethod
    def integrator(cls, gain: float) -> Filter:
        """Pure integrator g / (1 - z^-1)."""
        return cls((), (1.0,), float(gain))

    @classmethod
    def leaky(cls, forgetting: float, gain: float) -> Filter:
        """Leaky integrator g / (1 - alpha z^-1), alpha the forgetting factor (paper, Eq. stateINT)."""
        if not 0.0 <= forgetting <= 1.0:
            raise InputError(f"forgetting factor must be in [0, 1], got {forgetting:g}")
        return cls((), (float(forgetting),), float(gain))

    @classmethod
    def iir(cls, zeros, poles, gain: float) -> Filter:
        """General IIR filter from its zeros, poles and gain."""
        return cls(tuple(zeros), tuple(poles), float(gain))

    def with_gain(self, gain: float) -> Filter:
        return replace(self, gain=float(gain))

    @property
    def n_states(self) -> int:
        """N_f = N_alpha + N_beta, the RTC states this filter takes."""
        return len(self.zeros) + len(self.poles)

    def coefficients(self) -> tuple[np.ndarray, np.ndarray]:
        """(b, a) in powers of z^-1, gain included in b: H = (b0 + b1 z^-1 + ...)/(1 + a1 z^-1 + ...)."""
        return self.gain * _real_poly(self.zeros, "zeros"), _real_poly(self.poles, "poles")

    def frequency_response(self, w) -> np.ndarray:
        """H(e^{jw}) from the zeros, poles and gain (paper, Eq. tfIIR); w in rad/frame, 0..pi."""
        zi = np.exp(-1j * np.asarray(w, dtype=float))
        h = np.full(zi.shape, complex(self.gain))
        for beta in self.zeros:
            h *= 1.0 - beta * zi
        for alpha in self.poles:
            h /= 1.0 - alpha * zi
        return h

    def state_space_frequency_response(self, w) -> np.ndarray:
        """H(e^{jw}) = g C (I - A e^{-jw})^-1 B_unit from the RTC realisation (paper, Eq. stateIIR)."""
        A, B, C = self.unit_state_space()
        zi = np.exp(-1j * np.asarray(w, dtype=float))
        eye = np.eye(A.shape[0])
        systems = eye[None] - A[None] * zi.reshape(-1, 1, 1)
        x = np.linalg.solve(systems, np.broadcast_to(B, (zi.size, B.size))[..., None])[..., 0]
        return (self.gain * (x @ C)).reshape(zi.shape)

    def unit_state_space(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A, B_unit, C) of the realisation above: x(k) = A x(k-1) + g B_unit u(k), y(k) = C x(k)."""
        b = _real_poly(self.zeros, "zeros")  # monic: b[0] = 1
        poles = list(self.poles)
        integrator = 1.0 in poles
        if integrator:
            poles.remove(1.0)
        a = _real_poly(tuple(poles), "poles")
        na, nb = len(poles), len(self.zeros)
        n = self.n_states
        A = np.zeros((n, n))
        B = np.zeros(n)
        # Direct-form row of the recursion (y, or w when the integrator is split off): it reads
        # the na latest outputs at 0..na-1 and the nb latest scaled inputs at na..na+nb-1.
        row = np.zeros(n)
        row[:na] = -a[1:]
        row[na : na + nb] = b[1:]
        for k in range(1, na):
            A[k, k - 1] = 1.0
        for k in range(1, nb):
            A[na + k, na + k - 1] = 1.0
        if nb:
            B[na] = 1.0
        C = np.zeros(n)
        if na:  # state 0: y(k), or w(k) when the integrator is split off
            A[0] = row
            B[0] = b[0]
        if integrator:
            iy = n - 1  # y(k) = y(k-1) + w(k)
            A[iy] = row
            A[iy, iy] = 1.0
            B[iy] = b[0]
        C[n - 1 if integrator else 0] = 1.0
        return A, B, C


def unit_coefficients(num, den) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Time filters as recorded, one row per mode, H = (b0 + b1 z^-1 + ...) / (a0 + a1 z^-1 +
    ...), as (b / g, a / a0, g): the unit-gain filters and the loop gains g = b_k / a0, b_k the
    first non-zero numerator coefficient (AOT's "the first numerator is the loop gain").  A row
    whose numerator is all zero (a mode not controlled) has g = 0 and numerator [1, 0, ...];
    InputError for a denominator whose first coefficient is 0 (not a causal filter)."""
    b, a = np.atleast_2d(np.asarray(num, dtype=float)), np.atleast_2d(np.asarray(den, dtype=float))
    if b.shape[0] != a.shape[0] or not (np.all(np.isfinite(b)) and np.all(np.isfinite(a))):
        raise InputError(f"time filters need finite numerators and denominators, one row per mode (got {b.shape[0]} and {a.shape[0]} rows)")
    a0 = a[:, 0]
    if np.any(a0 == 0):
        raise InputError(f"time filter of mode {int(np.flatnonzero(a0 == 0)[0]) + 1}: a denominator starting with 0 is not a causal filter")
    nonzero = b != 0
    first = np.where(nonzero.any(axis=1), nonzero.argmax(axis=1), 0)
    bk = b[np.arange(len(b)), first]
    gains = bk / a0
    unit = np.where(nonzero.any(axis=1)[:, None], b / np.where(bk == 0, 1.0, bk)[:, None], np.eye(1, b.shape[1]))
    return unit, a / a0[:, None], gains


def filter_of_coefficients(b, a) -> tuple[Filter, int]:
    """(H', n) of a unit time filter in powers of z^-1 (``unit_coefficients``): H = z^-n H',
    the n leading zero numerator terms a pure delay of the controller, which a Filter of zeros
    and poles cannot hold; the models add it to the loop delay."""
    b, a = np.trim_zeros(np.asarray(b, dtype=float), "b"), np.trim_zeros(np.asarray(a, dtype=float), "b")
    n = int(np.argmax(b != 0)) if np.any(b != 0) else 0
    b = b[n:] if b.size else np.array([1.0])
    zeros = _roots(b) if b.size > 1 else ()
    poles = _roots(a) if a.size > 1 else (0.0,)
    return Filter(zeros, poles, float(b[0] / a[0])), n


def _roots(c: np.ndarray) -> tuple[complex, ...]:
    """The roots of a polynomial in z^-1 (those of z^n c(z^-1)): real ones as floats, and those
    within 1e-9 of z = 1 exactly 1.0, the integrator the RTC and the transfer functions single out."""
    out: list[complex] = []
    for r in np.roots(c):
        if abs(r.imag) <= 1e-12 * max(1.0, abs(r)):
            out.append(1.0 if abs(r.real - 1.0) < 1e-9 else float(r.real))
        else:
            out.append(complex(r))
    return tuple(out)


def coefficient_rows(filters) -> tuple[np.ndarray, np.ndarray]:
    """(num, den): each filter's ``coefficients`` (powers of z^-1) as the rows of two arrays,
    zero-padded to the longest: the time filters a record stores, one row per mode."""
    pairs = [h.coefficients() for h in filters]
    width = max(max(len(b), len(a)) for b, a in pairs)
    num, den = np.zeros((len(pairs), width)), np.zeros((len(pairs), width))
    for i, (b, a) in enumerate(pairs):
        num[i, : len(b)], den[i, : len(a)] = b, a
    return num, den
