"""Auxiliary loops (the paper's *auxloop*, Sec. MGM): tasks that run beside the closed loop
every ``period_frames``, read the latest telemetry window and may write RTC parameters between
two frames.

The closed loop knows only this interface:

* :class:`TelemetryWindow` - the last frames' records, read-only, with the gains and the slope
  sensitivity k that were in force during them;
* :class:`RtcParameters` - what a task may write: the modal gains (the diagonal of Delta), the
  slope sensitivity k (the RTC multiplies the slopes by k before reconstruction), a modal
  probe (a sinusoid the RTC adds to one mode's commands, as SOUL's disturbance injection), the
  reference-slope offsets (NCPA; subtracted after k) and a reset of the RTC's state (the loop
  opened and closed again);
* :class:`AuxLoop` - ``start`` once before the first frame, ``update`` every period; ``update``
  returns a record (numbers or arrays) stored in the telemetry as a time series.

Tasks run in the order they are given: a task that changes k (OGTL) runs before one that
sets gains from the same window (MGM), which then scales its gains by k_window / k_now (the
paper's step 7).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from ..control.ogtl import SENSITIVITY_RANGE
from ..errors import InputError


@dataclass(frozen=True)
class ModalProbe:
    """A sinusoid of ``amplitude_nm`` (peak) at ``frequency_hz`` added to the commands of
    ``mode`` (0-based) every frame: c(k) += a sin(2 pi f k / rate) M[:, mode]."""

    mode: int
    amplitude_nm: float
    frequency_hz: float

    def value(self, frame: int, rate_hz: float) -> float:
        return self.amplitude_nm * math.sin(2.0 * math.pi * self.frequency_hz * frame / rate_hz)


@dataclass(frozen=True)
class TelemetryWindow:
    """The last ``frames`` frames of telemetry (rows = frames), at fixed gains and k."""

    first_frame: int
    rate_hz: float
    delay_frames: float
    measured_modes: np.ndarray  # R s(k), s scaled by k (what the RTC reconstructs), nm
    command_modes: np.ndarray  # M^-1 c(k), nm (probe included)
    mirror_modes: np.ndarray  # the mirror during frame k, nm
    slopes: np.ndarray  # s(k) scaled by k
    flux: np.ndarray  # detected electrons per frame
    gains: np.ndarray  # (n_modes,) in force during the window
    sensitivity: float  # k in force during the window

    @property
    def frames(self) -> int:
        return self.measured_modes.shape[0]

    @property
    def seconds(self) -> float:
        return self.frames / self.rate_hz


class RtcParameters:
    """The RTC parameters an auxiliary loop may change between two frames (see the module
    docstring); applied from the next frame on."""

    def __init__(self, n_modes: int, gains: np.ndarray, apply_gains, sensitivity: float = 1.0, slope_offset: np.ndarray | None = None):
        self.n_modes = n_modes
        self._gains = np.asarray(gains, dtype=float).copy()
        self._apply_gains = apply_gains
        self.sensitivity = float(sensitivity)
        self.probe: ModalProbe | None = None
        self.reset_requested = False  # the loop zeroes the RTC's state before the next frame
        self.slope_offset = slope_offset  # in force: the RTC's input is k s - offset_scale slope_offset
        self.held_offset: np.ndarray | None = None  # loaded, not yet applied (``hold_slope_offset``)
        self.offset_scale = 1.0  # OGTL's estimate of k gamma of its probed mode (``scale_slope_offset``)

    @property
    def gains(self) -> np.ndarray:
        return self._gains.copy()

    def set_gains(self, gains) -> None:
        g = np.asarray(gains, dtype=float)
        if g.shape != (self.n_modes,) or not np.all(np.isfinite(g)) or np.any(g < 0):
            raise InputError(f"gains must be {self.n_modes} finite values >= 0")
        self._gains = g.copy()
        self._apply_gains(g)

    def set_sensitivity(self, k: float) -> None:
        lo, hi = SENSITIVITY_RANGE
        if not (math.isfinite(k) and lo <= k <= hi):
            raise InputError(f"slope sensitivity k must be in {lo:g}..{hi:g}, got {k:g}")
        self.sensitivity = float(k)

    def hold_slope_offset(self) -> None:
        """Keep the offsets out of the loop until ``apply_slope_offset`` (OGTL applies them once
        k is calibrated: at k = 1 they are over-applied by 1 / gamma; ``optics.ncpa``)."""
        if self.slope_offset is not None:
            self.held_offset, self.slope_offset = self.slope_offset, None

    def apply_slope_offset(self) -> bool:
        """Put held offsets in force from the next frame; True if it did."""
        if self.held_offset is None:
            return False
        self.slope_offset, self.held_offset = self.held_offset, None
        return True

    def scale_slope_offset(self, scale: float) -> None:
        """Scale the offsets by OGTL's estimate of k gamma (``ogtl.offset_scale``): they ask the
        pyramid for the slopes of the NCPA at its present optical gain, not at the one k was
        last calibrated to."""
        if not (math.isfinite(scale) and 0.0 <= scale <= 1.0):
            raise InputError(f"slope offset scale must be in 0..1, got {scale!r}")
        self.offset_scale = float(scale)

    def request_reset(self) -> None:
        """Open the loop and close it again from the next frame: the RTC's state zeta is set
        to zero (the commands restart from a flat mirror, which the delay line then reaches)."""
        self.reset_requested = True

    def set_probe(self, probe: ModalProbe | None) -> None:
        if probe is not None and not (0 <= probe.mode < self.n_modes):
            raise InputError(f"probe mode must be in 1..{self.n_modes}, got {probe.mode + 1}")
        self.probe = probe


class AuxLoop(ABC):
    """Base of the auxiliary loops."""

    name: str = "auxloop"

    def __init__(self, period_frames: int):
        if period_frames < 1:
            raise InputError(f"an auxiliary loop's period must be at least 1 frame, got {period_frames}")
        self.period_frames = int(period_frames)

    def start(self, rtc: RtcParameters, rate_hz: float) -> None:  # noqa: B027 - an optional hook, not abstract
        """Called once before the first frame (e.g. to set a probe)."""

    @abstractmethod
    def update(self, window: TelemetryWindow, rtc: RtcParameters) -> dict:
        """Read ``window``, write ``rtc``; return the record of this update."""
