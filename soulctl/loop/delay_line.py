"""The loop delay in the time domain: commands reach the mirror d frames after the
measurement, the fractional part by linear interpolation between frames,

    applied(k) = (1 - e) c(k - n) + e c(k - n - 1),   d = n + e,

exactly the plant z^-d = z^-n ((1 - e) + e z^-1) of ``soulctl.control.transfer.Plant``: the
sampled response of a held command seen by an integrating detector (docs/physics.md)."""

from __future__ import annotations

from collections import deque

import numpy as np

from ..control.delay import fractional_taps
from ..errors import InputError


class DelayLine:
    def __init__(self, n_commands: int, delay_frames: float):
        n, e = fractional_taps(delay_frames)
        if n < 1:
            raise InputError(f"the simulated loop needs a delay of at least 1 frame, got {delay_frames:g}")
        self.n, self.e = n, e
        self.delay_frames = float(delay_frames)
        zero = np.zeros(n_commands)
        self._history = deque([zero] * (n + 1), maxlen=n + 1)  # c(k-1) ... c(k-n-1), newest first

    def applied(self) -> np.ndarray:
        """The mirror command during frame k (before c(k) is known)."""
        h = self._history
        out = (1.0 - self.e) * h[self.n - 1]
        if self.e:
            out = out + self.e * h[self.n]
        return out

    def push(self, commands: np.ndarray) -> None:
        """Record c(k) at the end of frame k."""
        self._history.appendleft(np.asarray(commands, dtype=float).copy())
