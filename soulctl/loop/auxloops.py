"""The auxiliary loops soulctl runs beside the closed loop (interface in ``auxloop``):

* :class:`OgtlTask` - the optical gain tracking loop: a probe on mode 30, the slope
  sensitivity k driven so that the probed mode's chi stays at 1, held while the commands'
  RMS grows (``control.ogtl``);
* :class:`MgmTask` - the Modal Gain Machine: every period, per-mode gains from the
  pseudo-open-loop PSDs of the window (``control.mgm``), scaled by k_window / k_now when OGTL
  changed k in the same update (the paper's step 7);
* :class:`TrialAndErrorTask` - the three-group gain scan (``control.trial``);
* :class:`LiveMetricsTask` - modal residual RMS, a Strehl estimate and the guide star's
  magnitude from the detected flux, recorded every period.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..control import mgm, ogtl, trial
from ..control.delay import fractional_taps
from ..errors import InputError
from .auxloop import AuxLoop, ModalProbe, RtcParameters, TelemetryWindow
from .metrics import pseudo_open_loop


class OgtlTask(AuxLoop):
    name = "ogtl"

    def __init__(self, period_frames: int, settings: ogtl.OgtlSettings = ogtl.OgtlSettings()):
        super().__init__(period_frames)
        self.settings = settings
        self.frequency_hz = math.nan
        self._commands_rms: float | None = None  # of the previous window (the hold rule)

    def start(self, rtc: RtcParameters, rate_hz: float) -> None:
        self.frequency_hz = self.settings.probe_frequency(rate_hz)
        rtc.set_probe(ModalProbe(self.settings.mode - 1, self.settings.amplitude_nm, self.frequency_hz))

    def update(self, window: TelemetryWindow, rtc: RtcParameters) -> dict:
        m = self.settings.mode - 1
        chi = ogtl.optical_gain_estimate(window.measured_modes[:, m], window.mirror_modes[:, m], self.frequency_hz,
                                         window.rate_hz, window.first_frame)
        k = ogtl.updated_sensitivity(window.sensitivity, chi, self.settings.gain)
        others = np.arange(window.command_modes.shape[1]) != m  # the probe is not the loop's motion
        rms = float(np.sqrt(np.mean(window.command_modes[:, others] ** 2)))
        k, held = ogtl.held_sensitivity(window.sensitivity, k, rms, self._commands_rms, self.settings.hold_growth)
        self._commands_rms = rms
        rtc.set_sensitivity(k)
        return {"chi": chi, "optical_gain": chi / window.sensitivity, "sensitivity": k, "held": held}


class MgmTask(AuxLoop):
    """MGM on the window of each period.  ``chi``: the optical gains chi_i of the plant model
    (Eq. plant with gamma k): with OGTL active the optical-gain table normalised to the probed
    mode (OGTL keeps that one at 1), otherwise the table times the fixed k."""

    name = "mgm"

    def __init__(self, period_frames: int, machine: mgm.ModalGainMachine):
        super().__init__(period_frames)
        self.machine = machine

    def update(self, window: TelemetryWindow, rtc: RtcParameters) -> dict:
        n, _ = fractional_taps(window.delay_frames)
        usable = window.frames - n - 1  # the first n + 1 frames lack their commands
        if usable < mgm.min_frames(self.machine.settings):
            return {}
        pol = pseudo_open_loop(window.measured_modes / self.machine.chi, window.command_modes, window.delay_frames,
                               self.machine.structure)
        optimum, _ = self.machine.optimum(pol[n + 1 :])
        gains = mgm.update_gains(window.gains, optimum, self.machine.settings) * (window.sensitivity / rtc.sensitivity)
        rtc.set_gains(gains)
        return {"gains": gains, "optimum": optimum}


class TrialAndErrorTask(AuxLoop):
    """Scans the groups in order; each sequence is ``settle`` frames (not scored, the loop
    settling at the new gain) plus ``measure`` frames scored by the group's measured-mode RMS.
    When a group is done its best gain is set and kept; after the last group the task is idle."""

    name = "trial"

    def __init__(self, n_modes: int, scans: Sequence[np.ndarray], settle: int, measure: int):
        super().__init__(settle + measure)
        self.groups = trial.gain_groups(n_modes)
        if len(scans) != len(self.groups):
            raise InputError(f"trial-and-error needs one gain scan per group ({len(self.groups)}), got {len(scans)}")
        self.scans = [np.asarray(s, dtype=float) for s in scans]
        self.measure = measure
        self._group, self._index = 0, 0
        self._merits: list[float] = []
        self.best: list[float] = []

    @property
    def done(self) -> bool:
        return self._group >= len(self.groups)

    def _set_trial(self, rtc: RtcParameters) -> None:
        g = rtc.gains
        g[self.groups[self._group][1]] = self.scans[self._group][self._index]
        rtc.set_gains(g)

    def start(self, rtc: RtcParameters, rate_hz: float) -> None:
        self._set_trial(rtc)

    def update(self, window: TelemetryWindow, rtc: RtcParameters) -> dict:
        if self.done:
            return {}
        name, modes = self.groups[self._group]
        measured = window.measured_modes[-self.measure :, modes]
        merit = float(np.sqrt(np.mean(np.sum(measured**2, axis=1))))
        gain = float(self.scans[self._group][self._index])
        self._merits.append(merit)
        record = {"group": self._group, "gain": gain, "merit": merit, "best": math.nan}
        self._index += 1
        if self._index == len(self.scans[self._group]):
            best = trial.best_gain(self.scans[self._group], self._merits)
            self.best.append(best)
            record["best"] = best
            g = rtc.gains
            g[modes] = best
            rtc.set_gains(g)
            self._group, self._index, self._merits = self._group + 1, 0, []
        if not self.done and self._index < len(self.scans[self._group]):
            self._set_trial(rtc)
        return record


class LiveMetricsTask(AuxLoop):
    """Live metrics from the window, as the paper's monitoring auxloops:

    * modal residual RMS (nm): sqrt(sum_i <m_i^2>) of the measured modes over chi (the
      controlled modes only: the fitting error is invisible to the WFS);
    * Strehl estimate at ``wavelength_m``: exp(-(2 pi sigma / lambda)^2) with that RMS (an
      upper bound: no fitting error, no aliasing);
    * guide-star magnitude from the flux: m_ref - 2.5 log10(flux / flux_ref), with the
      photons per frame that ``reference_magnitude`` gives by the configure photometry."""

    name = "metrics"

    def __init__(self, period_frames: int, chi: np.ndarray, wavelength_m: float, reference_magnitude: float, reference_flux: float):
        super().__init__(period_frames)
        self.chi = np.asarray(chi, dtype=float)
        self.wavelength_nm = wavelength_m * 1e9
        self.reference_magnitude = reference_magnitude
        self.reference_flux = reference_flux

    def update(self, window: TelemetryWindow, rtc: RtcParameters) -> dict:
        residual = window.measured_modes / self.chi
        rms = float(np.sqrt(np.sum(np.mean(residual**2, axis=0))))
        flux = float(np.mean(window.flux))
        magnitude = self.reference_magnitude - 2.5 * math.log10(flux / self.reference_flux) if flux > 0 else math.nan
        return {"modal_rms_nm": rms, "strehl_estimate": math.exp(-((2 * math.pi * rms / self.wavelength_nm) ** 2)),
                "magnitude_estimate": magnitude}
