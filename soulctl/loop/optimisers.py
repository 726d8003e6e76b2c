"""The live optimisers as auxiliary loops: MGM (``mgm_machine``), trial-and-error
(``trial_scans``), OGTL (``ogtl_task``) and the safety net guarding them, and
``LiveOptimisers``, which `loop run --mgm --ogtl` runs beside the loop."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..control import mgm
from ..control import ogtl as ogtl_model
from ..control.gains import (
    DEFAULT_FORGETTING,
    LoopGains,
    gain_groups,
    nominal_loop,
    unit_loops,
)
from ..control.ogtl import OgtlSettings
from ..control.transfer import max_stable_gain
from ..control.trial import scan_around, scan_gains
from ..errors import InputError
from ..optics.cache import ArrayCache
from ..optics.calibration import Calibration
from ..optics.optical_gains import CHI_TABLE_SEEING_ARCSEC
from ..ranges import DURATION_S, PERIOD_S
from .auxloops import LiveMetricsTask, MgmTask, OgtlTask, SafetyNet
from .chi_model import mgm_chi, optical_gain_table
from .gain_policy import initial_gains
from .metrics import band_wavelength
from .run import RunRequest, closing_frames
from .schedule import TRIAL_VALUES, OptimizeRequest, check_probe, default_period_s, period_settings
from .simulation import ClosedLoop

TRIAL_TOP = 0.8  # fraction of the nominal (chi = 1) maximum stable gain the scan stays below
TRIAL_SPAN = 3.0  # the scan spans 1/TRIAL_SPAN to TRIAL_SPAN x the group's initial gain
SAFETY_CHECK_S = 0.1  # the safety net's check period (at least SAFETY_CHECK_MIN_FRAMES)
SAFETY_CHECK_MIN_FRAMES = 10
SAFETY_RUN_FRAMES = 5  # the net runs every 5 frames: its fast trip reacts within them


def mgm_machine(
    observation,
    structure,
    chi: np.ndarray,
    settings: mgm.MgmSettings,
    forgetting: float = DEFAULT_FORGETTING,
    delay_frames: float | None = None,
) -> mgm.ModalGainMachine:
    """MGM for the observation's filters (unit gain), plant chi_i z^-d and, on Tip/Tilt, the
    structural resonance when the frame rate samples it."""
    unit, ba = unit_loops(observation, structure, forgetting, len(chi))
    d = observation.delay_frames if delay_frames is None else delay_frames
    return mgm.ModalGainMachine(tuple(unit), chi, d, observation.frame_rate_hz, settings, ba)


def trial_shapes(initial: np.ndarray) -> list[np.ndarray]:
    """Per group, the initial gains over their mean: trial-and-error scans the group's mean gain
    and keeps this shape (the noise-aware initial gains lower the noise-dominated modes of a
    group; one gain for all of them raised those fourfold at R17.5), uniform where the initial
    gains are (the paper's one gain per group)."""
    out = []
    for _, modes in gain_groups(len(initial)):
        mean = float(np.mean(initial[modes]))
        out.append(initial[modes] / mean if mean > 0 else np.ones(modes.stop - modes.start))
    return out


def trial_scans(request: OptimizeRequest, chi: np.ndarray, initial: np.ndarray | None = None) -> list[np.ndarray]:
    """Per group, the mean gains trial-and-error scans, such that no mode of the group goes
    beyond TRIAL_TOP x the nominal maximum stable gain over its chi (the group's ``trial_shapes``
    applied).  With ``initial`` gains, a scan around the group's mean initial gain
    (``scan_around``: TRIAL_VALUES gains from 1/TRIAL_SPAN to TRIAL_SPAN x, and the initial gain
    itself, so that the group keeps it when no other gain does better): a scan from near zero
    chose a Tip/Tilt gain of 0.05 at R14.5, 1.0" (Strehl 0.42 -> 0.28 on the same turbulence),
    and one to 0.8 g_max ran noise-dominated R16.5-17.5 loops at k ~ 3 away.  Without,
    TRIAL_VALUES gains from 5 % of that top to the top (``scan_gains``)."""
    obs = request.run.observation
    structure = request.run.sampled_structure()
    shapes = trial_shapes(initial) if initial is not None else [np.ones(m.stop - m.start) for _, m in gain_groups(len(chi))]
    scans = []
    for (_, modes), shape in zip(gain_groups(len(chi)), shapes):
        g_max = max_stable_gain(nominal_loop(obs, 1.0, modes.start == 0, structure))
        top = TRIAL_TOP * min(g_max, 2.0) / max(1.0, float(np.max(shape * chi[modes])))
        centre = 0.0 if initial is None else float(np.mean(initial[modes]))
        scans.append(scan_around(centre, top, TRIAL_SPAN, TRIAL_VALUES) if centre > 0 else scan_gains(top, TRIAL_VALUES))
    return scans


@dataclass(frozen=True)
class LiveOptimisers:
    """`loop run --mgm [--ogtl]`: MGM and/or OGTL beside the loop for the whole run, from the
    run's initial gains, plus the live metrics.  Called by ``run.run`` once the calibration is
    known; returns the tasks and the initial gains (the run's, capped by ``capped_gains``)."""

    mgm: bool = True
    ogtl: bool = True
    period_s: float | None = None  # None: ``default_period_s``
    ogtl_settings: OgtlSettings = field(default_factory=OgtlSettings)
    chi_seeing_arcsec: float | None = None  # None: the run's seeing

    def check(self, observation, duration_s: float) -> None:
        """InputError for a period too short for MGM's PSDs, a run too short for one update
        after the loop has closed, or a probe beyond the modes."""
        period_s = self.period(observation)
        PERIOD_S.check(period_s, "--period")
        if self.mgm:
            period_settings(self._frames(observation), observation)
        rate = observation.frame_rate_hz
        need = self.frames_needed(observation)
        if need / rate > DURATION_S.hi:
            raise InputError(
                f"--period {period_s:g} s: the loop closes, then two updates need {need / rate:.4g} s, more than "
                f"the {DURATION_S.hi:g} s a run may last; shorten --period"
            )
        if round(duration_s * rate) < need:
            raise InputError(
                f"--duration must be at least {need / rate:.3g} s for --mgm/--ogtl at --period {period_s:g} s "
                f"(the loop closes, then two updates), got {duration_s:g} s"
            )
        if self.ogtl:
            check_probe(self.ogtl_settings, observation, period_s)

    def period(self, observation) -> float:
        """--period, or the default for the observation's frame rate (``default_period_s``)."""
        return self.period_s if self.period_s is not None else default_period_s(observation, self.ogtl_settings)

    def _frames(self, observation) -> int:
        return max(1, round(self.period(observation) * observation.frame_rate_hz))

    def frames_needed(self, observation) -> int:
        """Frames of a run in which the loop closes and the auxiliary loops then update twice."""
        return closing_frames(observation.frame_rate_hz) + 2 * self._frames(observation)

    def __call__(self, request: RunRequest, gains: LoopGains, calibration: Calibration, cache: ArrayCache, loop: ClosedLoop):
        obs = request.observation
        period = self._frames(obs)
        seeing = self.chi_seeing_arcsec or request.seeing_arcsec
        gamma = optical_gain_table(calibration, cache, seeing)
        chi = mgm_chi(gamma, self.ogtl, self.ogtl_settings.mode)  # ``plant_model`` of that table
        noise = loop.sensor.modal_noise_nm(calibration.reconstructor)
        ogtl = ogtl_task(self.ogtl_settings, period, calibration, cache, noise, seeing) if self.ogtl else None
        tasks: list = [ogtl] if ogtl is not None else []
        if self.mgm:
            machine = mgm_machine(obs, request.structure, chi, period_settings(period, obs), gains.forgetting)
            tasks.append(MgmTask(period, machine, ogtl))
        tasks.append(LiveMetricsTask(period, gamma, band_wavelength(request.band), obs.magnitude_r, loop.sensor.photons_per_frame))
        tasks.append(safety_net(obs.frame_rate_hz, tasks))
        return tasks, initial_gains(gains, request, calibration, cache, loop, chi, noise, self.ogtl, self.ogtl_settings.mode)


def ogtl_task(
    settings: OgtlSettings,
    period_frames: int,
    calibration: Calibration,
    cache: ArrayCache,
    noise: np.ndarray,
    chi_seeing_arcsec: float = CHI_TABLE_SEEING_ARCSEC,
) -> OgtlTask:
    """OGTL for this configuration: k bounded by 1 / gamma_probe at ``ogtl_model.WORST_SEEING_ARCSEC``
    (the optical model's table), no spiral judged up to 1 / gamma_probe at ``chi_seeing_arcsec``
    (MGM's plant model's seeing), the probe's amplitude from the settings or, by default, from the probed mode's WFS
    noise (``noise``: ``sensor.modal_noise_nm``) and that gamma (``ogtl_model.default_amplitude``)."""
    m = settings.mode - 1
    worst = optical_gain_table(calibration, cache, ogtl_model.WORST_SEEING_ARCSEC)[m]
    gamma = float(optical_gain_table(calibration, cache, chi_seeing_arcsec)[m])
    amplitude = settings.amplitude_nm
    if amplitude is None:
        amplitude = ogtl_model.default_amplitude(float(noise[m]), gamma, period_frames, settings.min_snr)
    k_model = 1.0 / gamma if gamma > 0 else math.inf
    return OgtlTask(period_frames, settings, k_max=1.0 / worst, amplitude_nm=amplitude, k_model=k_model)


def request_ogtl_task(request: OptimizeRequest, calibration: Calibration, cache: ArrayCache, noise: np.ndarray) -> OgtlTask | None:
    """A fresh OGTL task for ``request`` (``ogtl_task`` at its update period and χ seeing), or
    None when the request runs without OGTL: the run's, and each evaluation's own."""
    if not request.ogtl:
        return None
    return ogtl_task(request.ogtl_settings, request.frames(request.period), calibration, cache, noise, request.chi_seeing)


def safety_net(rate_hz: float, tasks) -> SafetyNet:
    """The safety net running every SAFETY_RUN_FRAMES frames and checking every SAFETY_CHECK_S
    (at least SAFETY_CHECK_MIN_FRAMES frames), damping those of ``tasks`` that can be damped
    (OGTL, MGM, trial-and-error)."""
    tuned = [t for t in tasks if t is not None and hasattr(t, "damp")]
    checks = max(1, round(max(SAFETY_CHECK_MIN_FRAMES, SAFETY_CHECK_S * rate_hz) / SAFETY_RUN_FRAMES))
    return SafetyNet(SAFETY_RUN_FRAMES, tuned, checks=checks)
