"""Loop transfer functions and robustness margins of one controlled mode (paper, Sec. 2.3).

The plant is P(z) = chi z^-d: chi the optical gain, d the loop delay in frames.  A fractional
d is realised as linear interpolation between frames, z^-d = z^-n ((1 - e) + e z^-1)
(``delay.fractional_taps``), so that the closed loop stays a rational function whose
stability is decided exactly by the roots of its characteristic polynomial.

With the controller H (``filters.Filter``), the open loop is L = H P, the sensitivity (the
rejection transfer function) S = 1/(1 + L) and the complementary sensitivity (the noise
transfer function) T = L/(1 + L).  Frequencies are in Hz, from near 0 to Nyquist.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..errors import InputError
from .delay import fractional_taps
from .filters import Filter

MINUS_3DB = 1.0 / math.sqrt(2.0)
VIBRATION_HZ = 13.0  # the LBT spider-arm line (paper, Tab. TT: rejection at 13 Hz)
RESONANCE_HZ = 127.0  # the ASM control-structure resonance (paper, Sec. 2.3)


@dataclass(frozen=True)
class Plant:
    """P(z) = chi z^-d (1 + G(z)) with the fractional delay as linear interpolation between
    frames; G is an optional structural resonance excited by the mirror's own commands
    (``soulctl.control.structure``), given by its (b, a) at the loop's rate."""

    delay_frames: float
    optical_gain: float = 1.0
    structure: tuple[tuple[float, ...], tuple[float, ...]] | None = None

    def __post_init__(self):
        fractional_taps(self.delay_frames)  # validates d >= 0, finite
        if not (self.optical_gain > 0 and math.isfinite(self.optical_gain)):
            raise InputError(f"optical gain chi must be a finite number > 0, got {self.optical_gain:g}")

    @classmethod
    def with_structure(cls, delay_frames: float, resonance, rate_hz: float, optical_gain: float = 1.0) -> Plant:
        b, a = resonance.coefficients(rate_hz)
        return cls(delay_frames, optical_gain, (tuple(map(float, b)), tuple(map(float, a))))

    def numerator(self) -> np.ndarray:
        """P's numerator coefficients in powers of z^-1."""
        n, e = fractional_taps(self.delay_frames)
        taps = [1.0 - e, e] if e > 0 else [1.0]
        num = self.optical_gain * np.concatenate([np.zeros(n), taps])
        if self.structure is None:
            return num
        b, a = (np.asarray(x) for x in self.structure)
        size = max(len(a), len(b))
        return np.convolve(num, np.pad(a, (0, size - len(a))) + np.pad(b, (0, size - len(b))))

    def denominator(self) -> np.ndarray:
        """P's denominator in powers of z^-1 (1 without a structural resonance)."""
        return np.array([1.0]) if self.structure is None else np.asarray(self.structure[1], dtype=float)

    def frequency_response(self, w) -> np.ndarray:
        zi = np.exp(-1j * np.asarray(w, dtype=float))
        n, e = fractional_taps(self.delay_frames)
        p = self.optical_gain * zi**n * ((1.0 - e) + e * zi)
        if self.structure is not None:
            b, a = (np.asarray(x) for x in self.structure)
            p = p * (1.0 + np.polyval(b[::-1], zi) / np.polyval(a[::-1], zi))
        return p


def frequency_grid(rate_hz: float, n: int = 3000) -> np.ndarray:
    """Frequencies (Hz) from rate/1e5 to Nyquist, both ends included: log-spaced for the low
    frequencies plus linear for the high ones, so that margins near Nyquist are resolved."""
    nyquist = rate_hz / 2.0
    f = np.union1d(np.geomspace(rate_hz * 1e-5, nyquist, n), np.linspace(nyquist / n, nyquist, n))
    f[-1] = nyquist
    return f


@dataclass(frozen=True)
class Loop:
    """One mode's control loop: a controller, a plant and the frame rate."""

    controller: Filter
    plant: Plant
    rate_hz: float

    def __post_init__(self):
        if not (self.rate_hz > 0 and math.isfinite(self.rate_hz)):
            raise InputError(f"frame rate must be a finite number > 0 Hz, got {self.rate_hz:g}")

    @property
    def nyquist_hz(self) -> float:
        return self.rate_hz / 2.0

    def with_gain(self, gain: float) -> Loop:
        return replace(self, controller=self.controller.with_gain(gain))

    def omega(self, f_hz) -> np.ndarray:
        """Angular frequency in rad per frame."""
        return 2.0 * np.pi * np.asarray(f_hz, dtype=float) / self.rate_hz

    def open_loop(self, f_hz) -> np.ndarray:
        """L(e^{jw}) = H P."""
        w = self.omega(f_hz)
        return self.controller.frequency_response(w) * self.plant.frequency_response(w)

    def sensitivity(self, f_hz) -> np.ndarray:
        """S = 1/(1 + L): the rejection of a disturbance."""
        return 1.0 / (1.0 + self.open_loop(f_hz))

    def complementary(self, f_hz) -> np.ndarray:
        """T = L/(1 + L): the propagation of measurement noise (the noise transfer function)."""
        L = self.open_loop(f_hz)
        return L / (1.0 + L)

    def characteristic_polynomial(self) -> np.ndarray:
        """a(z^-1) q(z^-1) + b(z^-1) p(z^-1) in powers of z^-1, H = b/a, P = p/q: its roots in
        z are the closed-loop poles."""
        b, a = self.controller.coefficients()
        bp = np.convolve(b, self.plant.numerator())
        ap = np.convolve(a, self.plant.denominator())
        size = max(ap.size, bp.size)
        return np.pad(ap, (0, size - ap.size)) + np.pad(bp, (0, size - bp.size))

    def closed_loop_poles(self) -> np.ndarray:
        return np.roots(self.characteristic_polynomial())

    def is_stable(self) -> bool:
        """All closed-loop poles strictly inside the unit circle."""
        poles = self.closed_loop_poles()
        return bool(poles.size == 0 or np.max(np.abs(poles)) < 1.0 - 1e-9)


_BISECTIONS = 60  # halvings of a grid step: below a float's resolution at any frame rate


def _crossings(fun, f: np.ndarray) -> list[float]:
    """Frequencies where fun (vectorised, real) changes sign on the grid, refined by bisection
    of every bracket at once to the float resolution (a vectorised bisection rather than
    scipy's brentq bracket by bracket: the same roots, and the CLI starts without scipy.optimize)."""
    v = fun(f)
    idx = np.nonzero(np.signbit(v[:-1]) != np.signbit(v[1:]))[0]
    lo, hi, v_lo = f[idx].astype(float), f[idx + 1].astype(float), v[idx]
    exact = v_lo == 0.0
    for _ in range(_BISECTIONS):
        mid = 0.5 * (lo + hi)
        v_mid = fun(mid)
        left = np.signbit(v_mid) == np.signbit(v_lo)  # the sign change is in [mid, hi]
        lo, v_lo, hi = np.where(left, mid, lo), np.where(left, v_mid, v_lo), np.where(left, hi, mid)
        lo, hi = np.where(exact, f[idx], lo), np.where(exact, f[idx], hi)
    return [float(x) for x in 0.5 * (lo + hi)]


def critical_gains(loop: Loop, f: np.ndarray | None = None) -> list[tuple[float, float]]:
    """(frequency, gain) pairs where the loop with that gain passes through -1: the unit-gain
    open loop L1 is real and negative there, and the gain is -1/L1."""
    unit = loop.with_gain(1.0)
    f = frequency_grid(loop.rate_hz) if f is None else f
    inner = f[f < loop.nyquist_hz * (1 - 1e-9)]
    out = []
    for fc in _crossings(lambda x: unit.open_loop(x).imag, inner):
        L1 = unit.open_loop(np.array([fc]))[0]
        if L1.real < 0:
            out.append((fc, -1.0 / L1.real))
    L1 = unit.open_loop(np.array([loop.nyquist_hz]))[0]  # real at Nyquist for a real system
    if L1.real < 0:
        out.append((loop.nyquist_hz, -1.0 / L1.real))
    return sorted(out, key=lambda x: x[1])


def max_stable_gain(loop: Loop, f: np.ndarray | None = None) -> float:
    """Upper end of the range of gains (0, g_max) over which the loop is stable, found from the
    critical gains and checked on the closed-loop poles; 0 if unstable at small gains, inf if
    no critical gain bounds it."""
    gains = [g for _, g in critical_gains(loop, f) if g > 0]
    if not gains:
        return math.inf if loop.with_gain(1e-6).is_stable() else 0.0
    if not loop.with_gain(0.5 * gains[0]).is_stable():
        return 0.0
    for i, g in enumerate(gains):
        above = 0.5 * (g + gains[i + 1]) if i + 1 < len(gains) else 1.5 * g
        if not loop.with_gain(above).is_stable():
            return g
    return math.inf


def check_stabilisable(controller: Filter, delay_frames: float, rate_hz: float, what: str) -> float:
    """The maximum stable gain of ``controller``'s shape on the plant z^-d; InputError naming
    ``what`` when no gain stabilises it (e.g. all poles at z = 1)."""
    g_max = max_stable_gain(Loop(controller.with_gain(1.0), Plant(delay_frames), rate_hz))
    if not g_max > 0:
        raise InputError(
            f"{what} (zeros {_roots_text(controller.zeros)}, poles {_roots_text(controller.poles)}) is unstable at every "
            f"gain at {rate_hz:g} Hz with a {delay_frames:.3g}-frame delay: no loop can run it"
        )
    return g_max


def _roots_text(roots) -> str:
    return "[" + ", ".join(f"{complex(r).real:.4g}" if complex(r).imag == 0 else f"{complex(r):.4g}" for r in roots) + "]"


# The closed loop's figures (from S and T): an unstable loop has none, since S and T then
# describe no steady state; its gain margin (the factor to lower the gain by), phase margin
# (negative) and maximum stable gain stay (``LoopAnalysis.figure``).
CLOSED_LOOP_FIGURES = ("modulus_margin", "modulus_margin_hz", "rejection_13hz", "noise_127hz", "rejection_bandwidth_hz", "bandwidth_hz")
UNSTABLE_NOTE = "the closed loop is unstable: S and T describe no steady state"


@dataclass(frozen=True)
class LoopAnalysis:
    """Robustness and performance figures of one loop (the rows of ``soulctl filter analyze``)."""

    rate_hz: float
    gain: float
    delay_frames: float
    optical_gain: float
    stable: bool
    gain_margin: float  # g_max / g; inf if no finite g_max
    phase_margin_deg: float | None  # min over |L| = 1 of 180 - |arg L|; < 0 if unstable; None: no crossing
    gain_crossover_hz: float | None
    modulus_margin: float  # min |1 + L|, the distance of the Nyquist curve from -1
    modulus_margin_hz: float
    max_stable_gain: float
    rejection_13hz: float | None  # |S(13 Hz)|
    noise_127hz: float | None  # |T(127 Hz)|
    rejection_bandwidth_hz: float | None  # first |S| = -3 dB
    bandwidth_hz: float | None  # first |T| = -3 dB, the closed-loop bandwidth

    def figure(self, name: str):
        """A figure as it may be reported: None for a closed-loop figure of an unstable loop."""
        return None if not self.stable and name in CLOSED_LOOP_FIGURES else getattr(self, name)

    def not_available(self) -> dict[str, str]:
        """The figures ``figure`` withholds, each with its reason."""
        return {} if self.stable else dict.fromkeys(CLOSED_LOOP_FIGURES, UNSTABLE_NOTE)

    def to_dict(self) -> dict:
        def clean(x):
            if isinstance(x, float) and not math.isfinite(x):
                return None if math.isnan(x) else "inf"
            return x

        return {k: clean(self.figure(k)) for k in self.__dict__} | {"not_available": self.not_available()}


def _at(fun, f_hz: float, nyquist: float) -> float | None:
    return float(abs(fun(np.array([f_hz]))[0])) if f_hz <= nyquist else None


def analyze(loop: Loop, vibration_hz: float = VIBRATION_HZ, resonance_hz: float = RESONANCE_HZ) -> LoopAnalysis:
    """Margins, rejection and bandwidth of a loop (stable or not: an unstable loop gets its
    figures too, with stable False and a gain margin below 1).

    Parameters
    ----------
    loop : Loop
        The controller, the plant chi z^-d (and the structure) and the frame rate.
    vibration_hz : float
        Where the rejection |S| is read (13 Hz, LBT's vibration).
    resonance_hz : float
        Where the noise transfer |T| is read (127 Hz, the structural resonance).

    Returns
    -------
    LoopAnalysis
        Gain, phase and modulus margins, the maximum stable gain, |S(vibration_hz)|,
        |T(resonance_hz)|, the -3 dB bandwidths and the verdict.
    """
    f = frequency_grid(loop.rate_hz)
    g = loop.controller.gain
    g_max = max_stable_gain(loop, f)
    stable = loop.is_stable()
    gain_margin = g_max / g if g > 0 else math.inf

    # Phase margin: at each frequency where |L| = 1, the phase change (lag or lead) that would
    # bring L onto -1, 180 deg - |arg L|; the smallest over all crossings, negative if the
    # loop is unstable.
    crossings = _crossings(lambda x: np.log(np.abs(loop.open_loop(x))), f)
    phase_margin = crossover = None
    for fc in crossings:
        pm = 180.0 - abs(float(np.degrees(np.angle(loop.open_loop(np.array([fc]))[0]))))
        if phase_margin is None or pm < phase_margin:
            phase_margin, crossover = pm, fc
    if phase_margin is not None and not stable:
        phase_margin = -phase_margin

    # Modulus margin: min |1 + L|, refined around the grid minimum.
    from scipy.optimize import minimize_scalar  # here: the CLI starts without scipy.optimize

    d = np.abs(1.0 + loop.open_loop(f))
    i = int(np.argmin(d))
    lo, hi = f[max(i - 1, 0)], f[min(i + 1, f.size - 1)]
    res = minimize_scalar(
        lambda x: abs(1.0 + loop.open_loop(np.array([x]))[0]), bounds=(lo, hi), method="bounded", options={"xatol": 1e-9 * loop.rate_hz}
    )
    mm, mm_f = (float(res.fun), float(res.x)) if res.fun < d[i] else (float(d[i]), float(f[i]))

    s_cross = _crossings(lambda x: np.abs(loop.sensitivity(x)) - MINUS_3DB, f)
    t_cross = _crossings(lambda x: np.abs(loop.complementary(x)) - MINUS_3DB, f)
    return LoopAnalysis(
        rate_hz=float(loop.rate_hz),
        gain=float(g),
        delay_frames=float(loop.plant.delay_frames),
        optical_gain=float(loop.plant.optical_gain),
        stable=stable,
        gain_margin=float(gain_margin),
        phase_margin_deg=phase_margin,
        gain_crossover_hz=crossover,
        modulus_margin=mm,
        modulus_margin_hz=mm_f,
        max_stable_gain=float(g_max),
        rejection_13hz=_at(loop.sensitivity, vibration_hz, loop.nyquist_hz),
        noise_127hz=_at(loop.complementary, resonance_hz, loop.nyquist_hz),
        rejection_bandwidth_hz=s_cross[0] if s_cross else None,
        bandwidth_hz=t_cross[0] if t_cross else None,
    )
