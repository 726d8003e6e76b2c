"""The loop delay of SOUL as a function of the frame rate (tables/delay_model.toml).

tau(f) = T + t_readout + t_computation + t_asm/2, with T = 1/f: half a frame for the mean age
of the light in an exposure, half a frame for the zero-order hold of the command, plus the
pure latencies.  In frames d = tau*f; its fractional part is modelled as linear interpolation
between frames (see ``fractional_taps``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .. import tables
from ..errors import InputError
from ..ranges import DELAY_TERM_MS


@dataclass(frozen=True)
class DelayModel:
    """The delay terms in milliseconds, as in tables/delay_model.toml and configuration files."""

    t_readout_ms: float
    t_computation_ms: float
    t_asm_ms: float
    source: str = ""

    def __post_init__(self):
        for name in ("t_readout_ms", "t_computation_ms", "t_asm_ms"):
            DELAY_TERM_MS.check(getattr(self, name), f"delay term {name}")

    @classmethod
    def from_table(cls, system: str = "soul") -> DelayModel:
        t = tables.delay_terms(system)
        return cls(
            t_readout_ms=float(t["t_readout_ms"]),
            t_computation_ms=float(t["t_computation_ms"]),
            t_asm_ms=float(t["t_asm_ms"]),
            source=str(t.get("source", "")),
        )

    @property
    def latency_s(self) -> float:
        """The part of the delay that does not scale with the frame period."""
        return (self.t_readout_ms + self.t_computation_ms + 0.5 * self.t_asm_ms) * 1e-3

    def total_s(self, frame_rate_hz: float) -> float:
        """Total loop delay in seconds."""
        if not (frame_rate_hz > 0 and math.isfinite(frame_rate_hz)):
            raise InputError(f"frame rate must be > 0 Hz, got {frame_rate_hz:g}")
        return 1.0 / frame_rate_hz + self.latency_s

    def frames(self, frame_rate_hz: float) -> float:
        """Total loop delay in frames (d in P(z) = chi z^-d)."""
        return self.total_s(frame_rate_hz) * frame_rate_hz


def fractional_taps(delay_frames: float) -> tuple[int, float]:
    """(n, e) such that z^-d = z^-n ((1 - e) + e z^-1), n = floor(d), 0 <= e < 1."""
    if not (delay_frames >= 0 and math.isfinite(delay_frames)):
        raise InputError(f"delay must be a finite number >= 0 frames, got {delay_frames:g}")
    n = math.floor(delay_frames)
    return n, delay_frames - n
