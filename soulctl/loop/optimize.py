"""Gain optimisation in the simulated loop (`soulctl optimize gains`, `loop run --mgm`).

One continuous closed loop in three phases:

1. *before*: ``measure_s`` at the initial gains (OGTL already running when asked);
2. *optimisation*: the optimiser live as an auxiliary loop - trial-and-error (the three-group
   scan, its length set by the scan) or MGM (every ``period_s`` for ``duration_s``);
3. *after*: ``measure_s`` at the optimised gains, frozen (OGTL still running).

Strehl ratio (long-exposure PSF), residual and Tip/Tilt jitter are measured over *before* and
*after*.  MGM's plant model takes chi_i from the optical-gain table of the calibration at a
reference correction level (0.8" seeing, the paper's choice), computed with the optical models
and cached with the calibration: with OGTL, gamma_i / gamma_30 (OGTL holds mode 30 at 1);
without, gamma_i times the fixed sensitivity k = 1.  With OGTL the loop starts at k = 1 /
gamma_30 of that table (OGTL then tracks the real one), so that neither optimiser scans while k
is still far from its value: at k = 1 a poorly corrected loop's effective gains are several
times lower than they will be once OGTL has converged.

Trial-and-error scans each group up to 0.8 x the nominal maximum stable gain divided by the
largest chi_i of the group (the same table): the scan stays stable for every mode of the group
as long as the table holds.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..control import mgm
from ..control.ogtl import OgtlSettings
from ..control.transfer import max_stable_gain
from ..control.trial import gain_groups, scan_gains
from ..errors import InputError
from ..optics.atmosphere import AtmosphereConfig
from ..optics.cache import ArrayCache, cache_key
from ..optics.calibration import Calibration
from ..optics.optical_gains import CorrectionLevel, optical_gains
from .auxloops import LiveMetricsTask, MgmTask, OgtlTask, TrialAndErrorTask
from .metrics import PsfAccumulator, band_wavelength
from .run import RunRequest, calibration_for, check_stability, default_gains, nominal_loop, sampled_structure
from .simulation import ClosedLoop, LoopDiverged, LoopGains, mode_filters

METHODS = ("trial", "mgm")
MIN_SEGMENT = 64  # frames: the shortest Welch segment MGM accepts
TRIAL_VALUES = 8  # gains per group
TRIAL_TOP = 0.8  # fraction of the nominal (chi = 1) maximum stable gain the scan reaches


@dataclass(frozen=True)
class OptimizeRequest:
    run: RunRequest  # observation, conditions, initial gains, band, seed, ...
    method: str = "mgm"
    duration_s: float = 5.0  # MGM's optimisation phase
    period_s: float = 1.0  # MGM's update period (the paper: 1 s)
    ogtl: bool = True
    ogtl_settings: OgtlSettings = field(default_factory=OgtlSettings)
    measure_s: float = 0.5  # before and after
    trial_sequence_s: float = 0.25  # one trial-and-error sequence (20 % of it settling)
    chi_seeing_arcsec: float = 0.8
    mgm_settings: mgm.MgmSettings | None = None  # None: segment from the period

    def __post_init__(self):
        if self.method not in METHODS:
            raise InputError(f"--method must be one of {', '.join(METHODS)}, got '{self.method}'")
        for name, lo, hi in (("duration_s", 0, 3600), ("period_s", 0, 600), ("measure_s", 0, 600), ("trial_sequence_s", 0, 60)):
            v = getattr(self, name)
            if not (math.isfinite(v) and lo < v <= hi):
                raise InputError(f"{name.replace('_s', '')} must be in {lo:g}..{hi:g} s (> 0), got {v:g}")
        rate = self.run.observation.frame_rate_hz
        if self.method == "mgm":
            self.settings_for_rate(rate)  # refuses a period too short for the PSDs
        if self.ogtl and self.ogtl_settings.mode > self.run.observation.modes:
            raise InputError(f"the OGTL probe mode {self.ogtl_settings.mode} is beyond the {self.run.observation.modes} controlled modes")

    def frames(self, seconds: float) -> int:
        return max(1, round(seconds * self.run.observation.frame_rate_hz))

    def settings_for_rate(self, rate_hz: float) -> mgm.MgmSettings:
        """MGM settings with the longest power-of-two Welch segment (<= 512) that gives 4
        segments in one period; InputError with the minimum period when even 64 does not fit."""
        period = self.frames(self.period_s)
        segment = 512
        while segment > MIN_SEGMENT and mgm.min_frames(mgm.MgmSettings(segment=segment)) > period:
            segment //= 2
        settings = self.mgm_settings or mgm.MgmSettings(segment=segment)
        need = mgm.min_frames(settings)
        if period < need:
            raise InputError(f"--period must be at least {need / rate_hz:.3g} s at {rate_hz:g} Hz ({need} frames: 4 PSD segments of "
                             f"{settings.segment} frames), got {self.period_s:g} s")
        return settings


@dataclass
class PhaseMetrics:
    strehl: float
    residual_nm: float
    tt_jitter_mas: float

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class OptimizeResult:
    request: OptimizeRequest
    initial_gains: np.ndarray
    gains: np.ndarray
    before: PhaseMetrics | None
    after: PhaseMetrics | None
    loop: ClosedLoop
    chi: np.ndarray | None
    diverged_at: int | None = None
    seconds: float = 0.0
    phases: dict = field(default_factory=dict)  # name -> (first frame, end frame)


def optical_gain_table(calibration: Calibration, cache: ArrayCache, seeing_arcsec: float = 0.8, screens: int = 4, seed: int = 1) -> np.ndarray:
    """gamma_i of the calibration's modes at the reference correction level, cached."""
    key = cache_key("optical-gains", {"calibration": calibration.setup.key(), "seeing": seeing_arcsec, "screens": screens, "seed": seed})
    hit = cache.load(key)
    if hit is not None:
        return hit["gains"]
    gains = optical_gains(calibration, CorrectionLevel(seeing_arcsec), screens, seed).gains
    cache.store(key, {"gains": gains})
    return gains


def mgm_chi(gamma: np.ndarray, ogtl: bool, probe_mode: int) -> np.ndarray:
    """chi_i of MGM's plant: gamma_i / gamma_probe with OGTL (chi = 1 on the probed mode),
    gamma_i (k = 1) without."""
    return gamma / gamma[probe_mode - 1] if ogtl else gamma.copy()


def mgm_machine(request: OptimizeRequest, calibration: Calibration, chi: np.ndarray) -> mgm.ModalGainMachine:
    obs = request.run.observation
    unit = mode_filters(obs, LoopGains(1.0, 1.0, 1.0), calibration.basis.n_modes)
    structure = sampled_structure(request.run.structure, obs.frame_rate_hz)
    ba = None if structure is None else tuple(tuple(map(float, x)) for x in structure.coefficients(obs.frame_rate_hz))
    return mgm.ModalGainMachine(tuple(unit), chi, obs.delay_frames, obs.frame_rate_hz, request.settings_for_rate(obs.frame_rate_hz), ba)


def trial_scans(request: OptimizeRequest, chi: np.ndarray) -> list[np.ndarray]:
    """Per group, TRIAL_VALUES gains up to TRIAL_TOP x the nominal maximum stable gain over
    the group's largest chi."""
    obs = request.run.observation
    structure = sampled_structure(request.run.structure, obs.frame_rate_hz)
    scans = []
    for _, modes in gain_groups(len(chi)):
        g_max = max_stable_gain(nominal_loop(obs, 1.0, modes.start == 0, structure))
        scans.append(scan_gains(TRIAL_TOP * min(g_max, 2.0) / max(1.0, float(np.max(chi[modes]))), TRIAL_VALUES))
    return scans


def _phase_metrics(loop: ClosedLoop, psf: PsfAccumulator, start: int, stop: int) -> PhaseMetrics:
    tm = loop.telemetry
    rms = np.asarray(tm.residual_rms_nm[start:stop])
    tt = np.asarray(tm.residual_modes[start:stop])[:, :2] * loop.mas_per_nm_tt
    return PhaseMetrics(psf.strehl, float(np.sqrt(np.mean(rms**2))), float(np.sqrt(np.mean(tt.var(axis=0)))))


def optimize(request: OptimizeRequest, cache: ArrayCache = ArrayCache(None), progress=None) -> OptimizeResult:
    """Run the three phases (see the module docstring).  ``progress(done, total)`` per frame."""
    r = request.run
    obs = r.observation
    structure = sampled_structure(r.structure, obs.frame_rate_hz)
    gains = r.gains or default_gains(obs, structure)
    if not r.allow_unstable:
        check_stability(obs, gains, structure)
    cal = calibration_for(r, cache)
    n_modes = cal.basis.n_modes
    gamma = optical_gain_table(cal, cache, request.chi_seeing_arcsec)
    chi = mgm_chi(gamma, request.ogtl, request.ogtl_settings.mode)
    k0 = 1.0 / gamma[request.ogtl_settings.mode - 1] if request.ogtl else 1.0
    if request.method == "mgm":
        optimiser = MgmTask(request.frames(request.period_s), mgm_machine(request, cal, chi))
        n_opt = request.frames(request.duration_s)
    else:
        sequence = request.frames(request.trial_sequence_s)
        settle = max(1, sequence // 5)
        optimiser = TrialAndErrorTask(n_modes, trial_scans(request, chi), settle, sequence - settle)
        n_opt = sequence * sum(len(s) for s in optimiser.scans)
    aux = [OgtlTask(request.frames(request.period_s), request.ogtl_settings)] if request.ogtl else []
    atmosphere = AtmosphereConfig.lbt_default(r.seeing_arcsec, r.L0_m, r.wind_m_s)
    loop = ClosedLoop(obs, cal, atmosphere, gains, vibrations=r.vibrations, noise=r.noise, seed=r.seed,
                      structure=structure, aux_loops=aux, sensitivity=k0)
    loop.add_aux_loop(LiveMetricsTask(request.frames(request.period_s), chi, band_wavelength(r.band), obs.magnitude_r,
                                      loop.sensor.photons_per_frame))
    initial = loop.rtc_parameters.gains
    n_measure = request.frames(request.measure_s)
    total = 2 * n_measure + n_opt
    wavelength = band_wavelength(r.band)
    psf_before, psf_after = PsfAccumulator(loop.pupil, wavelength), PsfAccumulator(loop.pupil, wavelength)
    done = 0

    def tick(_):
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total)

    result = OptimizeResult(request, initial, initial, None, None, loop, chi)
    t0 = time.perf_counter()
    try:
        loop.run(n_measure, psf=psf_before, skip=min(n_measure // 2, request.frames(0.05)), progress=tick)
        result.before = _phase_metrics(loop, psf_before, n_measure // 2, n_measure)
        result.phases["before"] = (0, n_measure)
        loop.add_aux_loop(optimiser)
        loop.run(n_opt, progress=tick)
        loop.remove_aux_loop(optimiser)
        result.phases["optimisation"] = (n_measure, n_measure + n_opt)
        result.gains = loop.rtc_parameters.gains
        start = loop.frame
        loop.run(n_measure, psf=psf_after, skip=min(n_measure // 2, request.frames(0.05)), progress=tick)
        result.after = _phase_metrics(loop, psf_after, start + n_measure // 2, loop.frame)
        result.phases["after"] = (start, loop.frame)
    except LoopDiverged as e:
        result.diverged_at = e.frame
        result.gains = loop.rtc_parameters.gains
    result.seconds = time.perf_counter() - t0
    return result
