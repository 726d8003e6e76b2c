"""The auxiliary loops soulctl runs beside the closed loop (interface in ``auxloop``):

* :class:`OgtlTask` - the optical gain tracking loop: a probe on mode 30, the slope
  sensitivity k driven so that the probed mode's chi stays at 1, held while the commands'
  RMS grows (``control.ogtl``);
* :class:`MgmTask` - the Modal Gain Machine: every period, per-mode gains from the
  pseudo-open-loop PSDs of the window (``control.mgm``), scaled by k_window / k_now when OGTL
  changed k in the same update (the paper's step 7); with OGTL, from its first calibrated k on;
* :class:`TrialAndErrorTask` - the three-group gain scan (``control.trial``);
* :class:`LiveMetricsTask` - modal residual RMS, a Strehl estimate and the guide star's
  magnitude from the detected flux, recorded every period.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from collections.abc import Sequence
from typing import Protocol

import numpy as np

from ..control import mgm, ogtl, trial
from ..control.delay import fractional_taps
from ..control.gains import gain_groups
from ..errors import InputError
from ..telemetry.figures import pseudo_open_loop
from .auxloop import AuxLoop, ModalProbe, RtcParameters, TelemetryWindow


class OgtlTask(AuxLoop):
    """OGTL (``control.ogtl``): the probe from ``start``, one k update per period with the
    reliability, bound, rate, spiral and growth rules; ``k_max`` the upper bound of k (1 /
    gamma_probe at the worst seeing, from the task's builder); ``k_model`` the k up to which
    no spiral is judged (1 / gamma_probe at the seeing of MGM's plant model); ``amplitude_nm`` the
    probe's amplitude when the settings leave it to the operating point."""

    name = "ogtl"

    def __init__(
        self,
        period_frames: int,
        settings: ogtl.OgtlSettings = ogtl.OgtlSettings(),
        k_max: float = ogtl.SENSITIVITY_RANGE[1],
        amplitude_nm: float | None = None,
        k_model: float = ogtl.MIN_SENSITIVITY,
    ):
        super().__init__(period_frames)
        self.settings = settings
        self.k_max = float(min(k_max, ogtl.SENSITIVITY_RANGE[1]))
        # a model without a finite k (gamma 0 or unknown) judges spirals from k = 1 on
        self.k_model = float(min(k_model, self.k_max)) if math.isfinite(k_model) else ogtl.MIN_SENSITIVITY
        self.amplitude_nm = settings.amplitude_nm or amplitude_nm or ogtl.PROBE_AMPLITUDE_NM
        self.frequency_hz = math.nan
        self.step_scale = 1.0  # the safety net halves it after a recovery
        self._commands_rms: float | None = None  # of the previous window (the growth rule)
        self.chi_now: float | None = None  # the latest chi of the probed mode that k acted on, at ``_chi_k``
        self._chi_k = 1.0  # the k chi_now is at: the one OGTL set last, unless the safety net restored another
        self._last: tuple[float, float] | None = None  # (k, chi_hat) of the last reliable estimate
        self.ceiling = math.inf  # k's ceiling after a spiral (``ogtl.spiralling``), for ``_ceiling_left`` reliable estimates
        self._ceiling_left = 0
        self._hold = ogtl.SPIRAL_HOLD  # the next spiral's ceiling lasts this long (doubled each time)

    def start(self, rtc: RtcParameters, rate_hz: float) -> None:
        self.frequency_hz = self.settings.probe_frequency(rate_hz)
        rtc.set_probe(ModalProbe(self.settings.mode - 1, self.amplitude_nm, self.frequency_hz))
        rtc.hold_slope_offset()  # NCPA offsets wait for a calibrated k (``ogtl.OFFSETS_CHI_TOLERANCE``)

    def damp(self) -> None:
        self.step_scale *= 0.5

    @property
    def calibrated(self) -> bool:
        """k has acted on a reliable estimate (``chi_now`` is known): before it, the loop's
        optical gain is unknown within the factor k_max, and k may yet move that far.  A
        safety-net restore to a k of before does not undo it: gamma is still known."""
        return self.chi_now is not None

    @property
    def gamma_now(self) -> float | None:
        """The probed mode's optical gain from the latest estimate k acted on (None before)."""
        return None if self.chi_now is None else self.chi_now / self._chi_k

    def follow(self, rtc: RtcParameters) -> None:
        """Carry ``chi_now`` to the k in force when another set it (the safety net's restore of
        a good state's k): chi = gamma k, and gamma is not what the restore changed.  Without
        this, MGM's gamma was off by the ratio of the two k."""
        if self.chi_now is not None and rtc.sensitivity != self._chi_k:
            self.chi_now *= rtc.sensitivity / self._chi_k
        self._chi_k = rtc.sensitivity

    def _set_ceiling(self, k: float) -> None:
        """k is not raised past ``k`` (its value before the spiral) for the hold, which doubles."""
        self.ceiling, self._ceiling_left, self._hold = k, self._hold, 2 * self._hold

    def _count_down(self) -> None:
        """One more reliable estimate without a spiral: the ceiling lifts when its hold is over."""
        self._ceiling_left = max(0, self._ceiling_left - 1)
        if self._ceiling_left == 0:
            self.ceiling = math.inf

    def update(self, window: TelemetryWindow, rtc: RtcParameters) -> dict:
        self.follow(rtc)
        m = self.settings.mode - 1
        est = ogtl.estimate(window.measured_modes[:, m], window.mirror_modes[:, m], self.frequency_hz, window.rate_hz, window.first_frame)
        others = np.arange(window.command_modes.shape[1]) != m  # the probe is not the loop's motion
        rms = float(np.sqrt(np.mean(window.command_modes[:, others] ** 2)))
        growing = ogtl.commands_growing(rms, self._commands_rms, self.settings.hold_growth)
        self._commands_rms = rms
        settings = dataclasses.replace(
            self.settings, gain=self.settings.gain * self.step_scale, max_step=1.0 + (self.settings.max_step - 1.0) * self.step_scale
        )
        k, status = ogtl.next_sensitivity(window.sensitivity, est, settings, min(self.k_max, self.ceiling), growing)
        reliable = status not in (ogtl.LOW_SNR, ogtl.NO_ESTIMATE)
        if reliable and self._last is not None and ogtl.spiralling(window.sensitivity, est.chi, self._last, self.k_model):
            k, status = self._last[0], ogtl.SPIRAL
            self._set_ceiling(k)
        elif reliable:
            self._last = (window.sensitivity, est.chi)
            self._count_down()
        # chi_now (MGM's gamma, the offsets' scale) only from an estimate k acted on: one made while
        # the commands grow is of a loop in transient, which OGTL itself does not trust to move k
        acted = status not in ogtl.HELD
        if acted:
            self.chi_now = est.chi * k / window.sensitivity
        elif self.chi_now is not None:
            self.chi_now *= k / self._chi_k
        rtc.set_sensitivity(k)
        self._chi_k = rtc.sensitivity
        if self.chi_now is not None:
            rtc.scale_slope_offset(ogtl.offset_scale(self.chi_now))
        calibrated = acted and self.chi_now is not None and abs(self.chi_now - 1.0) <= ogtl.OFFSETS_CHI_TOLERANCE
        applied = calibrated and rtc.apply_slope_offset()
        if applied:
            self._last = None  # their NCPA lowers gamma by design: no spiral judged across their entry
        return {
            "chi": est.chi,
            "chi_sigma": est.sigma,
            "snr": est.snr,
            "optical_gain": est.chi / window.sensitivity,
            "sensitivity": k,
            "status": status,
            "held": status in ogtl.HELD,
            "offsets_applied": bool(applied),
            "offset_scale": rtc.offset_scale,
            "mode": self.settings.mode,
            "amplitude_nm": self.amplitude_nm,
            "frequency_hz": self.frequency_hz,
            "k_max": self.k_max,
            "k_model": self.k_model,
            "k_ceiling": min(self.k_max, self.ceiling),
        }


class MgmTask(AuxLoop):
    """MGM on the window of each period.  ``chi``: the optical gains chi_i of the plant model
    (Eq. plant with gamma k): with OGTL active the optical-gain table normalised to the probed
    mode (OGTL keeps that one at 1), otherwise the table times the fixed k.

    With ``ogtl`` (the run's OGTL task), the model is scaled by what OGTL knows of the probed
    mode's optical gain gamma: chi_i = chi_model,i x gamma x k, gamma OGTL's latest chi
    that k acted on over its k.  Not an estimate held while the commands grew: at R16.5 (CI's
    short case) the only one past the SNR rule was such, 0.093 against the table's 0.177, and
    MGM's first update raised every gain ~10x.  Before OGTL has one (``OgtlTask.calibrated``)
    MGM waits: gains tuned at a k that OGTL then raises by up to k_max are over-driven by that
    factor once it does (R18.5 1.5": OGTL held k = 1 through the run, MGM raised every gain
    ~5x on the table's gamma, and the paired evaluation's OGTL, settling at k = 6.8, diverged;
    docs/physics.md, "An optimiser waits for a calibrated k").  The safety net's ``damp``
    halves rho.

    Memory of ``psd_updates`` windows (``mgm.PSD_UPDATES``, the newest included): the optimum
    of an update is of the mean prewhitened POL PSD of these windows, each rebuilt at the
    geometric mean of the gammas of the same updates (``ModalGainMachine.pol_spectra``: the
    POL's parts, so that a window's PSD follows a later gamma exactly).  The pseudo-open loop does not depend on the gains,
    so every window estimates the same PSD, and the mean of five has about 1/sqrt(5) of one's
    scatter; gamma changes with the turbulence over minutes, not from one 2-3 s update to the
    next, while OGTL's estimate of it scatters by 15-20 % at the faint end.  With one window
    and the latest gamma, MGM with OGTL ended 0.004-0.010 below the initial gains at R17.5 and
    R18.5, 0.6" (docs/physics.md).

    A mode's gain moves only where the mean PSD predicts a significant fall of J
    (``ModalGainMachine.significant``, each window's Welch segments counted); the record's
    ``held`` counts the modes that kept their gain (still carried to the new k)."""

    name = "mgm"

    def __init__(
        self,
        period_frames: int,
        machine: mgm.ModalGainMachine,
        ogtl: OgtlTask | None = None,
        psd_updates: int = mgm.PSD_UPDATES,
    ):
        super().__init__(period_frames)
        self.machine = machine
        self.ogtl = ogtl
        self.rho_scale = 1.0
        self.windows: deque[tuple[tuple, float, int]] = deque(maxlen=psd_updates)  # (POL spectra, k of the window, its Welch segments)
        self.gammas: deque[float] = deque(maxlen=psd_updates)

    def damp(self) -> None:
        self.rho_scale *= 0.5

    def gamma(self, rtc: RtcParameters) -> float:
        """The probed mode's optical gain as OGTL knows it now (it has run for this update;
        ``update`` asks only once it is calibrated), carried to the k in force; 1 without OGTL
        (the model's own)."""
        if self.ogtl is None:
            return 1.0
        self.ogtl.follow(rtc)
        gamma = self.ogtl.gamma_now
        return 1.0 if gamma is None else gamma

    def chi_scale(self, k: float) -> float:
        """chi of the probed mode at ``k`` relative to the model's: the memory's gamma x k with
        OGTL (geometric mean), 1 without."""
        return float(np.exp(np.mean(np.log(self.gammas)))) * k if self.ogtl is not None else 1.0

    def window_psds(self) -> np.ndarray:
        """The POL PSD of each window in the memory, rebuilt at the memory's chi scale (the
        update's optimum is of their mean)."""
        return np.array([mgm.psd_of_spectra(parts, 1.0 / self.chi_scale(k)) for parts, k, _ in self.windows])

    def update(self, window: TelemetryWindow, rtc: RtcParameters) -> dict:
        if self.ogtl is not None and not self.ogtl.calibrated:
            return {}  # nothing recorded, no gain moved: MGM's record count tells the waits
        n, _ = fractional_taps(window.delay_frames)
        usable = window.frames - n - 1  # the first n + 1 frames lack their commands
        if usable < mgm.min_frames(self.machine.settings):
            return {}
        mirror = pseudo_open_loop(np.zeros_like(window.command_modes), window.command_modes, window.delay_frames, self.machine.structure)
        measured = window.measured_modes / self.machine.chi
        spectra = self.machine.pol_spectra(measured[n + 1 :], mirror[n + 1 :])
        self.windows.append((spectra, window.sensitivity, mgm.segments_of(usable, self.machine.settings)))
        self.gammas.append(self.gamma(rtc))
        psd = np.mean(self.window_psds(), axis=0)
        optimum, info = self.machine.optimum_of_psd(psd)
        scale = self.chi_scale(window.sensitivity)
        moves = self.machine.significant(psd, window.gains * scale, optimum, [s for _, _, s in self.windows])
        optimum = optimum / scale
        settings = dataclasses.replace(self.machine.settings, rho=self.machine.settings.rho * self.rho_scale)
        gains = mgm.update_gains(window.gains, optimum, settings, moves) * (window.sensitivity / rtc.sensitivity)
        rtc.set_gains(gains)
        return {
            "gains": gains,
            "optimum": optimum,
            "chi_scale": scale,
            "noise_dominated": int(np.sum(info["noise_dominated"])),
            "held": int(np.sum(~moves)),
            "psd_windows": len(self.windows),
        }


class TrialAndErrorTask(AuxLoop):
    """Scans the groups in order, each up and down its scan (``trial.scan_order``: a gain's
    merit is the mean of its two visits); each sequence is ``settle`` frames (not scored, the loop
    settling at the new gain) plus ``measure`` frames scored by the group's measured-mode RMS;
    an update whose window is shorter than a sequence (the task started between two updates, or
    OGTL changed k during it) scores nothing and the sequence runs again.  A group's
    ``incumbents`` gain (one of its scan) is kept unless another is significantly better
    (``trial.chosen_gain``).  The merit is of R s over k (gamma x the residual): OGTL may
    change k between two sequences, and R s scales with it (at R14.5, 1.0" a fall of k by 6 %
    before the last sequence of modes 121-250 made their highest gain look best, and the
    Strehl ratio fell from 0.356 to 0.312).  A scanned gain g sets the group's modes to g x its ``shapes``
    (per mode, mean 1; uniform by default, the paper's one gain per group).
    When a group is done its best gain is set and kept; after the last group the task is idle."""

    name = "trial"

    def __init__(
        self,
        n_modes: int,
        scans: Sequence[np.ndarray],
        settle: int,
        measure: int,
        incumbents: Sequence[float | None] | None = None,
        shapes: Sequence[np.ndarray] | None = None,
    ):
        super().__init__(settle + measure)
        self.groups = gain_groups(n_modes)
        if len(scans) != len(self.groups):
            raise InputError(f"trial-and-error needs one gain scan per group ({len(self.groups)}), got {len(scans)}")
        self.scans = [np.asarray(s, dtype=float) for s in scans]
        self.incumbents = list(incumbents) if incumbents is not None else [None] * len(scans)  # kept unless beaten (``trial.chosen_gain``)
        # a scanned value g sets the group's modes to g x shape (mean 1): the paper's one gain per group when uniform
        self.shapes = (
            [np.ones(m.stop - m.start) for _, m in self.groups] if shapes is None else [np.asarray(x, dtype=float) for x in shapes]
        )
        self.measure = measure
        self.orders = [trial.scan_order(len(s)) for s in self.scans]  # up and down (``trial.scan_order``)
        self._group, self._index = 0, 0
        self._visits: list[int] = []  # the gains (indices into the scan) scored so far in this group ...
        self._merits: list[float] = []  # ... and their merits
        self._failed = False
        self.best: list[float] = []

    @property
    def done(self) -> bool:
        return self._group >= len(self.groups)

    def damp(self) -> None:
        """The safety net restored the gains during this sequence: its gain and the scan's higher
        ones score as the worst, and the group ends with the best of the others (each by the
        visits it had)."""
        self._failed = True

    def _set_trial(self, rtc: RtcParameters) -> None:
        g = self._with_best(rtc.gains)
        g[self.groups[self._group][1]] = self.scans[self._group][self.orders[self._group][self._index]] * self.shapes[self._group]
        rtc.set_gains(g)

    def _with_best(self, gains: np.ndarray) -> np.ndarray:
        """``gains`` with the groups already scanned at their best (a restore by the safety net
        may have set older gains)."""
        for (_, modes), best, shape in zip(self.groups, self.best, self.shapes):
            gains[modes] = best * shape
        return gains

    def start(self, rtc: RtcParameters, rate_hz: float) -> None:
        self._set_trial(rtc)

    def update(self, window: TelemetryWindow, rtc: RtcParameters) -> dict:
        if self.done:
            return {}
        if not self._failed and window.frames < self.period_frames:
            return {}  # the window began after the sequence (the task started off its period, or k changed): run it again
        name, modes = self.groups[self._group]
        measured = window.measured_modes[-self.measure :, modes] / window.sensitivity  # gamma x residual, whatever k
        scan, order = self.scans[self._group], self.orders[self._group]
        at = int(order[self._index])
        self._visits.append(at)
        if self._failed:  # this gain and the higher ones of the scan score as the worst: the group ends
            self._visits += list(range(at + 1, len(scan)))
            self._merits += [math.inf] * (len(scan) - at)
            self._index = len(order)
        else:
            self._merits.append(float(np.sqrt(np.mean(np.sum(measured**2, axis=1)))))
            self._index += 1
        self._failed = False
        record = {"group": self._group, "gain": float(scan[at]), "merit": self._merits[-1], "best": math.nan}
        if self._index == len(order):
            merits = trial.merits_by_gain(self._visits, self._merits, len(scan))
            # no finite merit: every gain failed, the group keeps what the safety net restored
            best = (
                trial.chosen_gain(scan, merits, self.incumbents[self._group])
                if np.isfinite(merits).any()
                else float(np.mean(rtc.gains[modes]))
            )
            self.best.append(best)
            record["best"] = best
            rtc.set_gains(self._with_best(rtc.gains))
            self._group, self._index, self._visits, self._merits = self._group + 1, 0, [], []
        if not self.done and self._index < len(self.orders[self._group]):
            self._set_trial(rtc)
        return record


class LiveMetricsTask(AuxLoop):
    """Live metrics from the window, as the paper's monitoring auxloops:

    * modal residual RMS (nm): sqrt(sum_i <m_i^2>) of the measured modes over gamma_i k, the
      optical-gain table's gamma_i and the window's k (the controlled modes only: the
      fitting error is invisible to the WFS; k as OGTL has it, so that the estimate does not
      move with k while OGTL settles);
    * Strehl estimate at ``wavelength_m``: exp(-(2 pi sigma / lambda)^2) with that RMS (an
      upper bound: no fitting error, no aliasing);
    * guide-star magnitude from the flux: m_ref - 2.5 log10(flux / flux_ref), with the
      photons per frame that ``reference_magnitude`` gives by the configure photometry."""

    name = "metrics"

    def __init__(self, period_frames: int, gamma: np.ndarray, wavelength_m: float, reference_magnitude: float, reference_flux: float):
        super().__init__(period_frames)
        self.gamma = np.asarray(gamma, dtype=float)
        self.wavelength_nm = wavelength_m * 1e9
        self.reference_magnitude = reference_magnitude
        self.reference_flux = reference_flux

    def update(self, window: TelemetryWindow, rtc: RtcParameters) -> dict:
        residual = window.measured_modes / (self.gamma * window.sensitivity)
        rms = float(np.sqrt(np.sum(np.mean(residual**2, axis=0))))
        flux = float(np.mean(window.flux))
        magnitude = self.reference_magnitude - 2.5 * math.log10(flux / self.reference_flux) if flux > 0 else math.nan
        return {
            "modal_rms_nm": rms,
            "strehl_estimate": math.exp(-((2 * math.pi * rms / self.wavelength_nm) ** 2)),
            "magnitude_estimate": magnitude,
        }


class Damped(Protocol):
    """A task the safety net can damp after a restore (OGTL, MGM, trial-and-error)."""

    def damp(self) -> None: ...


class SafetyNet(AuxLoop):
    """The RTC's safety net beside the optimisers.  It runs every ``period_frames`` (a few
    frames) and sums, over those frames and without the probed mode:

    * r, the residual the WFS sees at unit sensitivity, sqrt(sum_i <(R s)_i^2>) / k;
    * s, the RMS of the commands' frame-to-frame steps, sqrt(sum_i <(c_i(k) - c_i(k-1))^2>):
      the noise the loop propagates and any oscillation (the turbulence is slow);
    * c, the RMS of the commands of modes 3 and up, sqrt(sum_i <c_i^2>).

    Every ``checks`` runs (a check: ~0.1 s) it takes r, s and c over the check and keeps their
    means per state of the RTC parameters (gains and k).  The loop is in trouble when r exceeds
    ``threshold`` (3) x the lowest state mean of r (a tripled residual; in a healthy loop r
    moves by 2-3x from one check to the next with a strong vibration line), when s jumps to
    ``STEP_JUMP`` (6) x the previous state's (one MGM update changes a gain by at most 2x,
    ``mgm.MAX_GAIN_CHANGE``), or when s grows to ``GROWTH`` (2) or c to ``COMMAND_GROWTH`` (3) x their means over the
    state's first checks (an instability at fixed parameters, or a runaway: a loop the PWFS has
    lost grows in its commands while its WFS signal saturates and even falls; c is mostly the
    turbulence, which alone moves it by up to 2.3x within 2 s in a steady loop); on ``IN_A_ROW`` (3) checks in
    trouble in a row, or one beyond twice a limit, it acts.  Between checks, every run, it trips at once
    when c over the last ``period_frames`` exceeds ``FAST_GROWTH`` (2.5) x the previous state's
    mean (a runaway within a check, e.g. a trial gain the PWFS cannot hold).  Acting: the net
    opens the loop and closes it again (the RTC's state reset: a loop the PWFS has lost does
    not find its way back by itself) with the last good state's gains and k - a state is good
    when its mean r is within ``GOOD`` of the lowest; the state in trouble is none, even when
    its r is low (a runaway in the commands while the PWFS saturates), so it leaves the good
    states and the net goes back to the last other one (the state itself only when no other
    was good: then the reset alone acts) - halves the next steps of the ``tuned``
    tasks (their ``damp``), skips ``GRACE_CHECKS`` checks while the loop closes, and the
    optimisation continues.  After ``give_up`` checks in a row in trouble, restores
    notwithstanding (a restore and its grace checks do not end a streak; a check out of trouble
    does), it stops acting: the loop could not recover even at its last good state (the
    simulation's divergence test then decides)."""

    name = "safety"
    GOOD = 1.25
    MIN_CHECKS = 3  # checks a state needs before its means count
    STEP_JUMP = 6.0
    GROWTH = 2.0
    COMMAND_GROWTH = 3.0  # steady 10x10 loops at 0.8", 8 seeds x 2 s: c reached 2.3x its start
    FAST_GROWTH = 2.5
    GRACE_CHECKS = 2  # checks skipped after a restore, while the loop closes again
    IN_A_ROW = 3  # checks in trouble in a row before the net acts (fast runaways trip the fast rule)
    GOOD_MEMORY = 8  # good states kept, to go back past those that fell into trouble

    def __init__(self, period_frames: int, tuned: Sequence[Damped] = (), threshold: float = 3.0, give_up: int = 20, checks: int = 1):
        super().__init__(period_frames)
        if not (threshold > 1 and give_up >= 1 and checks >= 1):
            raise InputError(f"safety net: threshold must be > 1, give_up and checks >= 1, got {threshold!r}, {give_up!r}, {checks!r}")
        self.tuned = list(tuned)
        self.threshold = float(threshold)
        self.give_up = int(give_up)
        self.checks = int(checks)
        self.best = math.inf  # the lowest state mean of r
        self._goods: list[tuple[tuple[bytes, float], np.ndarray, float]] = []  # (state, gains, k) of the good states, latest last
        self._state: tuple[bytes, float] | None = None
        self._sum, self._count = np.zeros(3), 0
        self._start = np.full(3, math.inf)  # the state's means over its first MIN_CHECKS checks
        self._previous = np.full(3, math.inf)  # the previous state's means
        self._runs = np.zeros(6)  # sums of squares and their counts (r, s, c) over the current check
        self._n_runs = 0
        self._above = 0  # checks in a row in trouble since the last restore (when to act)
        self.streak = 0  # checks in a row in trouble, across restores (when to give up)
        self._grace = 0  # checks left to skip
        self.events = 0
        self.gave_up = False

    @property
    def good(self) -> tuple[np.ndarray, float] | None:
        """(gains, k) of the last good state, None before the first."""
        return (self._goods[-1][1], self._goods[-1][2]) if self._goods else None

    def _mark_good(self, window: TelemetryWindow) -> None:
        assert self._state is not None  # set by ``_enter``
        others = [g for g in self._goods if g[0] != self._state]
        self._goods = [*others[-(self.GOOD_MEMORY - 1) :], (self._state, window.gains, window.sensitivity)]

    @staticmethod
    def _sums(window: TelemetryWindow, rtc: RtcParameters) -> np.ndarray:
        """Sums of squares and counts of r, s and c over the window."""
        keep = np.ones(window.measured_modes.shape[1], dtype=bool)
        if rtc.probe is not None:
            keep[rtc.probe.mode] = False
        c = window.command_modes[:, keep]
        d = np.diff(c, axis=0)
        m = window.measured_modes[:, keep] / window.sensitivity
        return np.array([np.sum(m**2), len(m), np.sum(d**2), len(d), np.sum(c[:, 2:] ** 2), len(c)])

    @staticmethod
    def _rms(sums: np.ndarray) -> np.ndarray:
        return np.sqrt(sums[0::2] / np.maximum(sums[1::2], 1))

    def _enter(self, window: TelemetryWindow) -> None:
        """Start the statistics of a new state (or carry on with the current one)."""
        state = (window.gains.tobytes(), window.sensitivity)
        if state == self._state:
            return
        if self._count:
            self._previous = self._sum / self._count
        self._state, self._sum, self._count, self._start = state, np.zeros(3), 0, np.full(3, math.inf)
        self._runs, self._n_runs = np.zeros(6), 0

    def _fold(self, x: np.ndarray, window: TelemetryWindow) -> None:
        self._sum += x
        self._count += 1
        mean = self._sum / self._count
        if self._count == self.MIN_CHECKS:
            self._start = mean.copy()
        if self._count >= self.MIN_CHECKS:
            self.best = min(self.best, mean[0])
            if mean[0] <= self.GOOD * self.best:
                self._mark_good(window)

    def _trouble(self, x: np.ndarray) -> float:
        """The largest ratio of a measure to its limit (> 1: in trouble)."""
        ratios = (
            x[0] / (self.threshold * self.best),
            x[1] / (self.STEP_JUMP * self._previous[1]),
            x[1] / (self.GROWTH * self._start[1]),
            x[2] / (self.COMMAND_GROWTH * self._start[2]),
        )
        finite = [v for v in ratios if math.isfinite(v)]
        return float(max(finite)) if finite else 0.0

    def _restore(self, rtc: RtcParameters) -> None:
        assert self._goods  # a restore follows a good state (``update``)
        self._goods = [g for g in self._goods if g[0] != self._state] or self._goods  # the state in trouble is not good
        _, gains, k = self._goods[-1]
        rtc.set_gains(gains)
        rtc.set_sensitivity(k)
        rtc.request_reset()
        for task in self.tuned:
            task.damp()
        self.events += 1
        self._grace, self._above, self._state, self._count = self.GRACE_CHECKS * self.checks, 0, None, 0

    def update(self, window: TelemetryWindow, rtc: RtcParameters) -> dict:
        if window.frames < 3:
            return {}
        if self._grace:  # the loop is closing again after a restore
            self._grace -= 1
            return {}
        self._enter(window)
        sums = self._sums(window, rtc)
        self._runs += sums
        self._n_runs += 1
        now = self._rms(sums)
        if not self.gave_up and self.good is not None and now[2] > self.FAST_GROWTH * self._previous[2]:
            self._restore(rtc)
            return {
                "residual_nm": now[0],
                "steps_nm": now[1],
                "commands_nm": now[2],
                "trouble": math.nan,
                "restored": 1,
                "gave_up": int(self.gave_up),
                "streak": self.streak,
            }
        if self._n_runs < self.checks:
            return {}
        x = self._rms(self._runs)
        self._runs, self._n_runs = np.zeros(6), 0
        self._fold(x, window)
        trouble = self._trouble(x)
        self._above = self._above + 1 if trouble > 1 else 0
        self.streak = self.streak + 1 if trouble > 1 else 0
        restored = 0
        if not self.gave_up and self.good is not None and (self._above >= self.IN_A_ROW or trouble > 2):
            if self.streak > self.give_up:
                self.gave_up = True
            else:
                self._restore(rtc)
                restored = 1
        return {
            "residual_nm": x[0],
            "steps_nm": x[1],
            "commands_nm": x[2],
            "trouble": trouble,
            "restored": restored,
            "gave_up": int(self.gave_up),
            "streak": self.streak,
        }


def gave_up_at(records: dict) -> int | None:
    """The frame at which the safety net gave up, from its records (``aux_arrays("safety")``):
    the loop could not recover even at its last good state, the exit status 3 of the commands
    that run it.  None when it did not give up (or did not run)."""
    given_up = np.flatnonzero(np.asarray(records.get("gave_up", ())) == 1)
    return int(records["frame"][given_up[0]]) if given_up.size else None


def could_not_recover(telemetry) -> str | None:
    """The failure of a run whose safety net gave up (``TelemetryRecorder`` of the run), None
    if it did not (or ran no net): what `loop run`, `optimize gains` and `sweep` report with
    exit status 3 or status "diverged"."""
    frame = gave_up_at(telemetry.aux_arrays(SafetyNet.name)) if SafetyNet.name in telemetry.aux else None
    return None if frame is None else f"the safety net could not recover the loop (gave up at frame {frame})"


def summary(records: dict) -> dict:
    """What the auxiliary loops did, from the telemetry's records (``TelemetryRecorder.aux_arrays`` per
    task name): OGTL's probe, bound and update statuses, the frame its NCPA offsets entered
    (None: not in this run); MGM's updates and noise-dominated modes; the safety net's
    restores."""
    out: dict = {}
    og = records.get("ogtl", {})
    if len(og.get("frame", [])):
        status = og["status"].astype(int)
        out["ogtl"] = {
            "updates": int(status.size),
            "probe_mode": int(og["mode"][-1]),
            "probe_amplitude_nm": float(og["amplitude_nm"][-1]),
            "probe_frequency_hz": float(og["frequency_hz"][-1]),
            "k_max": float(og["k_max"][-1]),
            "statuses": {ogtl.STATUS[i]: int(np.sum(status == i)) for i in np.unique(status)},
            "ncpa_offsets_at_frame": next((int(f) for f, a in zip(og["frame"], og.get("offsets_applied", ())) if a), None),
        }
    mg = records.get("mgm", {})
    if len(mg.get("frame", [])):
        out["mgm"] = {"updates": int(len(mg["frame"])), "noise_dominated_modes_last": int(mg["noise_dominated"][-1])}
    sf = records.get("safety", {})
    if len(sf.get("frame", [])):
        out["safety"] = {
            "restores": int(np.sum(sf["restored"])),
            "restored_at_frames": sf["frame"][sf["restored"] == 1].tolist(),
            "gave_up": bool(sf["gave_up"][-1]),
            "gave_up_at_frame": gave_up_at(sf),
            "longest_streak": int(np.max(sf["streak"])) if "streak" in sf else 0,
        }
    return out
