"""The loop's stability when its modes couple: the mirror moved against the calibration
(mis-registration, fidelity issue item 4) makes the measured modes R D' c instead of c, with
the modal coupling Q = R D' (the identity when registered).

The RTC (paper Eq. 1) runs one filter per mode; modes 3-last share the leaky integrator's
shape and differ only by their gain g_i and optical gain chi_i, so their loop
h(z) P(z) diag(g chi) Q decouples on the eigenvectors of diag(g chi) Q into scalar loops
mu_j h(z) P(z).  Eigenmode j is stable iff the roots of a(z^-1) q(z^-1) + mu_j b(z^-1) p(z^-1)
lie inside the unit circle (h = b/a, P = p/q).  mu_j is complex once the mirror moves: its
phase eats the loop's phase margin, and the loop is lost when one eigenmode's phase exceeds
what its gain leaves.  Tip/Tilt (their own filter and the structural resonance) are analysed
on Q's 2x2 block; their coupling to the other modes is neglected (||Q[2:, :2]|| / ||Q[:2, :2]||
is 0.14 at one pitch of shift).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from .gains import LoopSettings, unit_loops
from .transfer import Loop, Plant

MARGIN_SCALES = np.union1d(np.geomspace(1e-3, 1e4, 71), [1.0])  # factors on diag(g chi) searched for the margin


@dataclass(frozen=True)
class CouplingStability:
    """The coupled loop's verdict: its eigenmodes, how many are unstable, the least stable
    closed-loop pole, and the margin (the largest factor on every g chi up to which all
    eigenmodes stay stable; > 1 stable with that much gain to spare, < 1 lost)."""

    eigenmodes: int
    unstable: int
    largest_pole: float  # |z| of the least stable closed-loop pole
    margin: float
    largest_phase_deg: float  # |arg mu| of the most rotated eigenmode
    registered_unstable: int = 0  # modes the gains alone leave unstable (Q = I, the mirror registered); counted when lost

    @property
    def stable(self) -> bool:
        return self.unstable == 0

    def unstable_text(self) -> str:
        """'N of its M eigenmodes are unstable (...)' for the failure messages."""
        cure = f"stable only with the gains x {self.margin:.2f}" if self.margin > 0 else "no common factor on the gains stabilises them"
        pole = f"closed-loop pole at |z| = {self.largest_pole:.3f}"
        own = ""
        if self.registered_unstable:
            own = f"; the gains alone leave {self.registered_unstable} modes unstable with the mirror registered"
        return f"{self.unstable} of its {self.eigenmodes} eigenmodes are unstable ({pole}; {cure}{own})"

    def figures_text(self) -> str:
        """'U of N (largest pole |z| ..., gain margin x...)' for the tables."""
        margin = "unbounded" if math.isinf(self.margin) else f"x{self.margin:.2f}"
        return f"{self.unstable} of {self.eigenmodes} (largest pole |z| {self.largest_pole:.3f}, gain margin {margin})"

    def to_dict(self) -> dict:
        """JSON-ready: an unbounded figure (a margin stable at every factor searched, a pole at
        infinity) is "inf", as ``transfer.LoopAnalysis`` writes it."""
        d = {k: ("inf" if isinstance(v, float) and math.isinf(v) else v) for k, v in self.__dict__.items()}
        return d | {"stable": self.stable}


def _polynomials(unit: Loop) -> tuple[np.ndarray, np.ndarray]:
    """(a q, b p) of the unit-gain loop, padded to one length, in powers of z^-1."""
    b, a = unit.controller.coefficients()
    ap = np.convolve(a, unit.plant.denominator())
    bp = np.convolve(b, unit.plant.numerator())
    n = max(ap.size, bp.size)
    return np.pad(ap, (0, n - ap.size)), np.pad(bp, (0, n - bp.size))


def pole_radii(unit: Loop, mu: np.ndarray) -> np.ndarray:
    """The largest closed-loop pole modulus of each scalar loop mu_j h(z) P(z) (complex mu_j),
    from the companion matrices of a q + mu_j b p, all at once; inf where the leading
    coefficient vanishes (a pole at infinity: a plant without delay and mu_j = -1/(b0 p0))."""
    ap, bp = _polynomials(unit)
    poly = ap[None, :] + np.asarray(mu, dtype=complex)[:, None] * bp[None, :]
    lead = poly[:, :1]
    degenerate = np.abs(lead[:, 0]) <= 1e-12 * np.abs(poly).max(axis=1)
    poly = poly / np.where(degenerate[:, None], 1.0, lead)
    n = poly.shape[1] - 1
    if n == 0:
        return np.where(degenerate, math.inf, 0.0)
    companion = np.zeros((len(mu), n, n), dtype=complex)
    companion[:, 0, :] = -poly[:, 1:]
    companion[:, np.arange(1, n), np.arange(n - 1)] = 1.0
    return np.where(degenerate, math.inf, np.abs(np.linalg.eigvals(companion)).max(axis=1))


def _radii(groups: list[tuple[Loop, np.ndarray]], scale: float) -> np.ndarray:
    return np.concatenate([pole_radii(unit, scale * mu) for unit, mu in groups])


def _margin(groups: list[tuple[Loop, np.ndarray]]) -> float:
    """The largest factor s such that every eigenmode of s diag(g chi) Q is stable for all
    factors up to s, to 1e-9 relative (0 if no factor stabilises it, inf if none of the
    ``MARGIN_SCALES`` up to 1e4 destabilises it)."""
    previous = 0.0
    for s in MARGIN_SCALES:
        if not np.all(_radii(groups, s) < 1.0):
            break
        previous = s
    else:
        return math.inf
    if previous == 0.0:
        return 0.0
    lo, hi = previous, s
    while hi / lo > 1 + 1e-9:
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if np.all(_radii(groups, mid) < 1.0) else (lo, mid)
    return float(lo)


def coupling_stability(coupling: np.ndarray, gains_chi: np.ndarray, tip_tilt_unit: Loop, unit: Loop) -> CouplingStability:
    """The verdict for the modal coupling Q (n x n) with the loop gains g_i chi_i; ``tip_tilt_unit``
    and ``unit``: the unit-gain loops of Tip/Tilt and of the other modes (see the module).
    Modes at gain 0 feed nothing back and are left out (as ``gains.check_stability`` skips
    them); an eigenvalue 0 of the others (a singular Q) is judged: an integrator's pole at 1."""
    q, g = np.asarray(coupling, dtype=float), np.asarray(gains_chi, dtype=float)
    groups = []
    for loop, modes in ((tip_tilt_unit, np.arange(min(2, len(g)))), (unit, np.arange(2, len(g)))):
        fed = modes[g[modes] != 0]
        groups.append((loop, np.linalg.eigvals(g[fed, None] * q[np.ix_(fed, fed)]) if fed.size else np.zeros(0, complex)))
    mu = np.concatenate([m for _, m in groups])
    if mu.size == 0:  # every gain 0: nothing is fed back
        return CouplingStability(0, 0, 0.0, math.inf, 0.0)
    radii = _radii(groups, 1.0)
    phases = np.degrees(np.abs(np.angle(mu[mu != 0]))) if np.any(mu != 0) else np.zeros(1)
    return CouplingStability(len(mu), int(np.sum(radii >= 1.0)), float(radii.max()), _margin(groups), float(phases.max()))


def registration_verdict(
    observation: LoopSettings, structure, forgetting: float, coupling: np.ndarray, gains_chi: np.ndarray, delay_frames: float
) -> CouplingStability:
    """``coupling_stability`` with the configuration's own unit loops: Tip/Tilt's filter on
    z^-d and the 127 Hz structure (when the frame rate samples it), the other modes' leaky
    integrator on z^-d; the verdict `loop run` gives at the end of a run and `rtc check` before
    an upload.  A lost loop also counts the eigenmodes its gains leave unstable with the mirror
    registered (gains run with --allow-unstable), so that the message does not blame the
    mis-registration alone."""
    filters, ba = unit_loops(observation, structure, forgetting, observation.modes)
    rate = observation.frame_rate_hz
    tip_tilt = Loop(filters[0], Plant(delay_frames, 1.0, ba) if ba is not None else Plant(delay_frames), rate)
    other = Loop(filters[-1], Plant(delay_frames), rate)
    verdict = coupling_stability(coupling, gains_chi, tip_tilt, other)
    return verdict if verdict.stable else replace(verdict, registered_unstable=unstable_alone(gains_chi, tip_tilt, other))


def unstable_alone(gains_chi: np.ndarray, tip_tilt_unit: Loop, unit: Loop) -> int:
    """Modes whose own loop is unstable at g_i chi_i: Q = I, the mirror registered."""
    g = np.asarray(gains_chi, dtype=float)
    n_tt = min(2, len(g))
    radii = np.concatenate([pole_radii(loop, mu[mu != 0]) for loop, mu in ((tip_tilt_unit, g[:n_tt]), (unit, g[n_tt:]))])
    return int(np.sum(radii >= 1.0))
