"""Assembly of the RTC matrices Lambda, Delta, Xi, Sigma from per-mode filters (paper, the
mixed-control equations after Eq. stateRTC):

    Lambda = blockdiag(A_1, A_2, ...)              (forgetting factors for leaky integrators)
    Xi     = blockdiag(B_unit,1, B_unit,2, ...) R  (R: modes x slopes reconstruction matrix)
    Delta  = blockdiag(g_1 I, g_2 I, ...)          (diagonal, the only place the gains live)
    Sigma  = M blockdiag(C_1, C_2, ...)            (M: commands x modes, modes-to-commands)

States are laid out in mode order; a mode without a filter takes no state and is not
controlled (zero gain).  N_I + sum N_f must not exceed the RTC's state size (672 for SOUL).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..optics.asm import N_ACTUATORS
from .filters import Filter
from .gains import mode_gains, state_gains

SOUL_STATE_SIZE = N_ACTUATORS  # one state per actuator


@dataclass(frozen=True)
class ModeBlock:
    """Where one controlled mode lives in the RTC state."""

    mode: int
    offset: int
    n_states: int


@dataclass(frozen=True)
class RTCMatrices:
    Lambda: np.ndarray  # (n_states, n_states)
    Xi: np.ndarray  # (n_states, n_slopes)
    Sigma: np.ndarray  # (n_commands, n_states)
    Delta: np.ndarray  # (n_states,) the diagonal of Delta
    blocks: tuple[ModeBlock, ...]
    n_modes: int

    @property
    def n_states(self) -> int:
        return self.Lambda.shape[0]

    @property
    def used_states(self) -> int:
        return sum(b.n_states for b in self.blocks)

    def delta_from_gains(self, gains: Sequence[float] | np.ndarray) -> np.ndarray:
        """The diagonal of Delta for one gain per mode (n_modes values; uncontrolled modes ignored)."""
        g = np.asarray(gains, dtype=float)
        if g.shape != (self.n_modes,):
            raise InputError(f"gains: expected {self.n_modes} values (one per mode), got shape {g.shape}")
        return state_gains(self.blocks, self.n_states, g)

    def mode_gains(self, delta: np.ndarray | None = None) -> np.ndarray:
        """One gain per mode read from Delta (zero for uncontrolled modes)."""
        return mode_gains(self.blocks, self.n_modes, self.Delta if delta is None else delta)

    def controller(self, n_threads: int = 0):
        """The C++ real-time controller with these matrices and gains.

        n_threads: OpenMP threads for its step(), 0..64 (0 = automatic); outside, ValueError."""
        from .._core import RealTimeController

        rtc = RealTimeController(self.Lambda, self.Xi, self.Sigma, n_threads=n_threads)
        rtc.set_state_gains(self.Delta.astype(np.float32))
        return rtc


def modes_that_fit(filters: Sequence[Filter | None], state_size: int) -> int:
    """How many leading modes of ``filters`` fit in ``state_size`` states."""
    used = 0
    for i, f in enumerate(filters):
        used += f.n_states if f is not None else 0
        if used > state_size:
            return i
    return len(filters)


def build_rtc(
    filters: Sequence[Filter | None],
    reconstructor: np.ndarray,
    modes_to_commands: np.ndarray,
    state_size: int = SOUL_STATE_SIZE,
) -> RTCMatrices:
    """Assemble Lambda, Xi, Sigma, Delta of the RTC equation (paper, Eq. RTC):
    zeta(k) = Lambda zeta(k-1) + Delta Xi s(k), c(k) = Sigma zeta(k).

    Parameters
    ----------
    filters : sequence of Filter or None
        One per mode (None: not controlled); modes beyond ``len(filters)`` are not controlled.
    reconstructor : ndarray, (n_modes, n_slopes)
        R: the modes of the slopes.
    modes_to_commands : ndarray, (n_commands, n_modes)
        M: the actuator commands of each mode.
    state_size : int
        The RTC's state vector length (SOUL's 672 by default); the filters' states must fit.

    Returns
    -------
    RTCMatrices
        Lambda, Xi, Sigma, the diagonal of Delta and each mode's block of states.
    """
    R = np.asarray(reconstructor, dtype=float)
    M = np.asarray(modes_to_commands, dtype=float)
    if R.ndim != 2 or M.ndim != 2:
        raise InputError(f"R and M must be matrices, got shapes {R.shape} and {M.shape}")
    n_modes, n_slopes = R.shape
    if M.shape[1] != n_modes:
        raise InputError(f"M: expected shape (n_commands, {n_modes}) to match R's {n_modes} modes, got {M.shape}")
    if len(filters) > n_modes:
        raise InputError(f"{len(filters)} filters given but R has only {n_modes} modes")
    needed = sum(f.n_states for f in filters if f is not None)
    if needed > state_size:
        fit = modes_that_fit(filters, state_size)
        raise InputError(
            f"the filters need {needed} states but the RTC has {state_size}: with these filters only the first {fit} modes fit"
        )

    Lambda = np.zeros((state_size, state_size))
    Xi = np.zeros((state_size, n_slopes))
    Sigma = np.zeros((M.shape[0], state_size))
    Delta = np.zeros(state_size)
    blocks = []
    offset = 0
    for mode, f in enumerate(filters):
        if f is None:
            continue
        A, B, C = f.unit_state_space()
        n = f.n_states
        s = slice(offset, offset + n)
        Lambda[s, s] = A
        Xi[s, :] = np.outer(B, R[mode])
        Sigma[:, s] = np.outer(M[:, mode], C)
        Delta[s] = f.gain
        blocks.append(ModeBlock(mode, offset, n))
        offset += n
    return RTCMatrices(Lambda, Xi, Sigma, Delta, tuple(blocks), n_modes)
