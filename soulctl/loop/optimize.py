"""Gain optimisation in the simulated loop (`soulctl optimize gains`, `loop run --mgm`).

One continuous closed loop in phases:

0. *closing*: the loop closes at the initial gains and k = 1 (``closing_frames``: 0.1 s, at
   least 50 frames), as a real loop is closed before its auxiliary loops start; stretched so
   that *before* ends on an update boundary (MGM's windows are then whole periods, in step
   with OGTL's updates);
   *settling* (with OGTL): OGTL starts from k = 1; ``OGTL_SETTLING_PERIODS`` to
   ``OGTL_MAX_SETTLING_PERIODS`` updates for k to settle (``_settled``);
1. *before*: ``measure_s`` at the initial gains (OGTL running when asked);
2. *optimisation*: the optimiser live as an auxiliary loop - trial-and-error (the three-group
   scan, its length set by the scan) or MGM (every ``period_s`` for ``duration_s``); with OGTL
   only if it has a calibrated k by the end of *before* (a reliable estimate k acted on), otherwise the
   phase runs at the initial gains and the result says why (``held``);
3. *after*: ``measure_s`` at the optimised gains, frozen (OGTL still running);
4. *evaluation*: the initial and the optimised gains, each in a loop closed afresh on the run's
   own turbulence and noise (``evaluate``): with OGTL closed much as the run was (k = 1 for
   ``closing_frames``, not stretched to an update boundary; then OGTL from k = 1 for
   OGTL_MAX_SETTLING_PERIODS updates, the run's longest settling, and at least
   EVALUATION_SETTLE_S: k is the loop's state, which OGTL keeps, not the optimiser's output);
   then OGTL stops (its probe stays) and both loops' windows run at the k *before*'s OGTL
   settled to (``FrozenK``): with OGTL running through them, the two loops' k paths part and
   the windows differ by them as much as by the gains; without OGTL, at k = 1.

Strehl ratio (long-exposure PSF), residual and Tip/Tilt jitter of the evaluation are the
result's *before* and *after*: a paired comparison, the two differing by the gains alone;
those of the run's own phases (``during_run``) differ by the turbulence of their time too.

MGM's plant model takes chi_i from the optical-gain table of the calibration at the run's
seeing (the paper tabulates 0.8"), computed with the optical models and cached with the
calibration: with OGTL, gamma_i / gamma_30 (OGTL holds mode 30 at 1); without, gamma_i times
the fixed sensitivity k = 1. OGTL starts from k = 1 once the loop is closed and settles (4 to
12 updates, until one that moved k by its own rule moves log k by less than 0.1) before anything is measured, so that
neither optimiser scans while k is still far from it. (Starting it at 1/gamma_30 of the table
instead over-drove the loops whose real optical gain was higher than the table's - a 0.6" loop
has a higher gamma than the 0.8" reference - and before the loop is closed the open-loop
residual is far outside the PWFS's linear range.) The initial gains come from the operating
point (``initial_gains``), the update period from the frame rate (``default_period_s``), and a
safety net guards every phase after the closing (``SafetyNet``). Trial-and-error scans each
group's mean gain geometrically from 1/3 to 3 x its initial value (and that value itself, kept
unless beaten by more than the merit's scatter), the modes keeping the shape of their initial
gains, no mode beyond 0.8 x the nominal maximum stable gain over its chi_i (the same table).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np

from .. import defaults
from ..control import mgm
from ..control import ogtl as ogtl_model
from ..control.coupling import CouplingStability
from ..control.delay import fractional_taps
from ..control.gains import (
    DEFAULT_FORGETTING,
    LoopGains,
    capped_gains,
    check_stability,
    gain_groups,
    nominal_loop,
    unit_loops,
)
from ..control.ogtl import OgtlSettings
from ..control.transfer import max_stable_gain
from ..control.trial import scan_around, scan_gains
from ..disturbance.modal_psd import cutoff_hz, modal_psd
from ..disturbance.turbulence import TurbulenceTipTilt
from ..errors import InputError
from ..optics.atmosphere import LAMBDA_REF_M, AtmosphereConfig
from ..optics.cache import ArrayCache
from ..optics.calibration import Calibration
from ..optics.optical_gains import CHI_TABLE_SEEING_ARCSEC
from ..optics.pupil import LBT_DIAMETER_M
from ..ranges import DURATION_S, EVALUATION_WINDOWS, MEASURE_S, MIN_MEASURE_FRAMES, OPTIMISATION_S, PERIOD_S, PROBE_MIN_CYCLES, SEQUENCE_S
from .auxloop import RtcParameters
from .auxloops import LiveMetricsTask, MgmTask, OgtlTask, SafetyNet, TrialAndErrorTask, could_not_recover
from .chi_model import mgm_chi, optical_gain_table, plant_model
from .metrics import band_wavelength
from .run import RunRequest, calibration_for, closed_loop_for, closing_frames, registration_stability
from .simulation import ClosedLoop, LoopDiverged

METHODS = ("trial", "mgm")
MIN_SEGMENT = 64  # frames: the shortest Welch segment MGM accepts ...
MAX_SEGMENT = 512  # ... and the longest it takes from a window
MGM_RESOLUTION_HZ = 1.0  # the default period holds 4 segments with bins at most this wide (``resolving_segment``)
DEFAULT_DURATION_S = 5.0  # MGM's default optimisation phase: at least this ...
DEFAULT_UPDATES = 5  # ... and this many update periods
MIN_SEQUENCE = 10  # frames of one trial-and-error sequence (a fifth of them settling)
DEFAULT_SEQUENCE_S = 0.25  # the default trial-and-error sequence, at least DEFAULT_SEQUENCE_FRAMES
DEFAULT_SEQUENCE_FRAMES = 100
TRIAL_VALUES = 8  # gains per group
TRIAL_TOP = 0.8  # fraction of the nominal (chi = 1) maximum stable gain the scan stays below
TRIAL_SPAN = 3.0  # the scan spans 1/TRIAL_SPAN to TRIAL_SPAN x the group's initial gain
INITIAL_GAIN_FRACTION = 0.5  # initial gains capped at this fraction of the plant model's g_max / chi
OGTL_SETTLING_PERIODS = 4  # OGTL updates before the "before" measurement, at least ...
OGTL_MAX_SETTLING_PERIODS = 12  # ... and at most, until k has settled (``_settled``)
SETTLED_LOG_STEP = 0.1  # k has settled when its last update, a measured one, changed log k by less than this
DEFAULT_PERIOD_S = 1.0  # the shortest default update period (``default_period_s``)
SAFETY_CHECK_S = 0.1  # the safety net's check period (at least SAFETY_CHECK_MIN_FRAMES)
SAFETY_CHECK_MIN_FRAMES = 10
SAFETY_RUN_FRAMES = 5  # the net runs every 5 frames: its fast trip reacts within them
# The paired evaluation's settling at k after the closing (``evaluate``): a steady state for any
# gains the optimisers return.  Measured at R16.5, 1.0", 250 Hz: MGM's gains (lower on Tip and the
# noise-dominated modes) close from the open loop in ~0.6 s, the initial gains in ~0.2 s; with
# 0.2 s the evaluation measured MGM's gains mid-transient (Strehl 0.129 -> 0.111), with 1 s in
# the steady state (0.127 -> 0.152; over 1-3 s the residual is 386 against 401 nm).
EVALUATION_SETTLE_S = 1.0
# An optimiser with OGTL starts only once OGTL has a calibrated k (``OgtlTask.calibrated``); the
# result's ``held`` when its settling and *before* ended without one:
UNCALIBRATED_K = "OGTL had acted on no reliable probe estimate when the optimiser was to start: k uncalibrated, the initial gains kept"
OPTIMISER_OGTL = True  # `optimize gains` and a sweep's optimised cases run OGTL unless told not to


@dataclass(frozen=True)
class OptimizeRequest:
    run: RunRequest  # observation, conditions, initial gains, band, seed, ...
    method: str = "mgm"
    duration_s: float | None = None  # MGM's optimisation phase; None: ``default_duration_s``
    period_s: float | None = None  # MGM's and OGTL's update period; None: ``default_period_s``
    ogtl: bool = OPTIMISER_OGTL
    ogtl_settings: OgtlSettings = field(default_factory=OgtlSettings)
    measure_s: float = defaults.MEASURE_S  # before and after, in the run and each window of the paired evaluation
    trial_sequence_s: float | None = None  # one trial-and-error sequence (20 % settling); None: ``default_sequence_s``
    chi_seeing_arcsec: float | None = None  # the optical-gain table's seeing; None: the run's (``chi_seeing``)
    mgm_settings: mgm.MgmSettings | None = None  # None: segment from the period
    windows: int = defaults.EVALUATION_WINDOWS  # consecutive windows of the paired evaluation (``evaluate``)
    window_s: float | None = None  # one evaluation window; None: measure_s

    def __post_init__(self):
        if self.period_s is None:
            object.__setattr__(self, "period_s", default_period_s(self.run.observation, self.ogtl_settings))
        if self.duration_s is None:
            object.__setattr__(self, "duration_s", default_duration_s(self.period))
        if self.trial_sequence_s is None:
            object.__setattr__(self, "trial_sequence_s", default_sequence_s(self.run.observation))
        if self.chi_seeing_arcsec is None:
            object.__setattr__(self, "chi_seeing_arcsec", self.run.seeing_arcsec)
        if self.method not in METHODS:
            raise InputError(f"--method must be one of {', '.join(METHODS)}, got '{self.method}'")
        for name, option, accepted in (
            ("duration_s", "--duration", OPTIMISATION_S),
            ("period_s", "--period", PERIOD_S),
            ("measure_s", "--measure", MEASURE_S),
            ("trial_sequence_s", "--sequence", SEQUENCE_S),
            ("windows", "--windows", EVALUATION_WINDOWS),
        ):
            accepted.check(getattr(self, name), option)
        if self.window_s is None:
            object.__setattr__(self, "window_s", self.measure_s)
        MEASURE_S.check(self.window_s, "the evaluation window")
        obs = self.run.observation
        if self.frames(min(self.measure_s, self.window)) < MIN_MEASURE_FRAMES:
            raise InputError(
                f"--measure must be at least {MIN_MEASURE_FRAMES / obs.frame_rate_hz:.3g} s at {obs.frame_rate_hz:g} Hz "
                f"({MIN_MEASURE_FRAMES} frames), got {min(self.measure_s, self.window):.10g} s"
            )
        if self.method == "mgm":
            self.settings_for_rate(obs.frame_rate_hz)  # refuses a period too short for the PSDs
            if self.duration < self.period:
                raise InputError(f"--duration ({self.duration:g} s) must hold at least one MGM update period (--period {self.period:g} s)")
        if self.method == "trial" and self.frames(self.sequence) < MIN_SEQUENCE:
            raise InputError(
                f"--sequence must be at least {MIN_SEQUENCE / obs.frame_rate_hz:.3g} s at {obs.frame_rate_hz:g} Hz "
                f"({MIN_SEQUENCE} frames), got {self.trial_sequence_s:g} s"
            )
        if self.ogtl:
            check_probe(self.ogtl_settings, obs, self.period)

    def frames(self, seconds: float) -> int:
        return max(1, round(seconds * self.run.observation.frame_rate_hz))

    # the fields' values, resolved by __post_init__
    @property
    def period(self) -> float:
        return _resolved(self.period_s)

    @property
    def duration(self) -> float:
        return _resolved(self.duration_s)

    @property
    def sequence(self) -> float:
        return _resolved(self.trial_sequence_s)

    @property
    def window(self) -> float:
        return _resolved(self.window_s)

    @property
    def chi_seeing(self) -> float:
        return _resolved(self.chi_seeing_arcsec)

    def settings_for_rate(self, rate_hz: float) -> mgm.MgmSettings:
        """MGM settings for windows of one period (see ``period_settings``)."""
        return self.mgm_settings or period_settings(self.frames(self.period), self.run.observation)


def _resolved(value: float | None) -> float:
    assert value is not None  # set by __post_init__
    return value


def resolving_segment(rate_hz: float) -> int:
    """The shortest power-of-two Welch segment, from MIN_SEGMENT to MAX_SEGMENT, whose bins are
    at most MGM_RESOLUTION_HZ wide (MAX_SEGMENT where none is).  Coarser bins hide the
    low-frequency disturbance a slow, noisy loop must reject in the DC bin MGM leaves out:
    at R16.5, 250 Hz, 1.0", 64-frame segments (3.9 Hz) put the Tip/Tilt optimum at 0.23, 128
    and 256 frames at 0.55 and 0.58, by the same telemetry (docs/physics.md)."""
    segment = MIN_SEGMENT
    while segment < MAX_SEGMENT and rate_hz / segment > MGM_RESOLUTION_HZ:
        segment *= 2
    return segment


def default_period_s(observation, settings: OgtlSettings = OgtlSettings()) -> float:
    """The default update period of MGM and OGTL: 1 s, lengthened (to a whole 0.1 s) where the
    frame rate needs more for MGM's 4 Welch segments of ``resolving_segment`` frames after the
    frames the delay leaves without commands, or for the probe's PROBE_MIN_CYCLES cycles: 1 s
    at 1361-1700 Hz, 1.2 s at 1148 Hz, 1.8 s at 750 Hz, 2.6 s at 250-500 Hz, 3.3 s at 100 Hz
    (the paper: an optimisation step takes 5-10 s, updates about every 5 s on sky)."""
    rate = observation.frame_rate_hz
    n, _ = fractional_taps(observation.delay_frames)
    need = mgm.min_frames(mgm.MgmSettings(segment=resolving_segment(rate))) + n + 1
    seconds = max(DEFAULT_PERIOD_S, need / rate, PROBE_MIN_CYCLES / settings.probe_frequency(rate))
    return math.ceil(round(seconds * 10, 9)) / 10


def shortest_period_s(observation, settings: OgtlSettings = OgtlSettings()) -> float:
    """The shortest update period MGM and OGTL accept (to a whole ms): MGM's 4 Welch segments of
    MIN_SEGMENT frames after the frames the delay leaves without commands, and the probe's
    PROBE_MIN_CYCLES cycles (a smoke test's period: ``cli.quick``)."""
    rate = observation.frame_rate_hz
    n, _ = fractional_taps(observation.delay_frames)
    need = mgm.min_frames(mgm.MgmSettings(segment=MIN_SEGMENT)) + n + 1
    seconds = max(need / rate, PROBE_MIN_CYCLES / settings.probe_frequency(rate))
    return math.ceil(round(seconds * 1000, 9)) / 1000


def default_duration_s(period_s: float) -> float:
    """MGM's default optimisation phase: DEFAULT_UPDATES update periods, at least DEFAULT_DURATION_S."""
    return max(DEFAULT_DURATION_S, round(DEFAULT_UPDATES * period_s, 9))


def default_sequence_s(observation) -> float:
    """The default trial-and-error sequence: 0.25 s, at least 100 frames (a low gain's loop at a
    low frame rate needs them to settle and to be scored through the noise), to a whole 0.01 s."""
    seconds = max(DEFAULT_SEQUENCE_S, DEFAULT_SEQUENCE_FRAMES / observation.frame_rate_hz)
    return math.ceil(round(seconds * 100, 9)) / 100


def check_probe(settings: OgtlSettings, observation, period_s: float) -> None:
    """InputError for an OGTL probe beyond the controlled modes, above Nyquist, or too slow
    for the lock-in: its period must fit ``PROBE_MIN_CYCLES`` times in an update period."""
    if settings.mode > observation.modes:
        raise InputError(
            f"--probe-mode {settings.mode} is beyond the {observation.modes} controlled modes (accepted 1..{observation.modes})"
        )
    f = settings.probe_frequency(observation.frame_rate_hz)
    if f * period_s < PROBE_MIN_CYCLES:
        raise InputError(
            f"--probe-frequency {f:.10g} Hz makes {f * period_s:.3g} cycles per --period of {period_s:g} s: the lock-in "
            f"needs at least {PROBE_MIN_CYCLES} (a probe frequency of at least {PROBE_MIN_CYCLES / period_s:.4g} Hz)"
        )


def period_settings(period_frames: int, observation) -> mgm.MgmSettings:
    """MGM settings for a window of one period (``welch_settings``; InputError names --period)."""
    n, _ = fractional_taps(observation.delay_frames)
    return welch_settings(period_frames, observation.frame_rate_hz, "--period", dropped=n + 1)


def welch_settings(frames: int, rate_hz: float, what: str, dropped: int = 0) -> mgm.MgmSettings:
    """MGM settings with the longest power-of-two Welch segment (<= MAX_SEGMENT) that gives MGM's 4
    segments in ``frames`` less the ``dropped`` first ones (the loop delay leaves n + 1 frames
    of a window without their commands); InputError naming ``what`` and its minimum when even
    64-frame segments do not fit."""
    usable = frames - dropped
    segment = MAX_SEGMENT
    while segment > MIN_SEGMENT and mgm.min_frames(mgm.MgmSettings(segment=segment)) > usable:
        segment //= 2
    settings = mgm.MgmSettings(segment=segment)
    need = mgm.min_frames(settings) + dropped
    if frames < need:
        raise InputError(
            f"{what} must be at least {need / rate_hz:.3g} s at {rate_hz:g} Hz ({need} frames: {mgm.MIN_SEGMENTS} PSD "
            f"segments of {segment} frames after the {dropped} the loop delay leaves without commands), "
            f"got {frames / rate_hz:.3g} s ({frames} frames)"
        )
    return settings


@dataclass
class PhaseMetrics:
    strehl: float  # the paired evaluation's: the mean of its windows'
    residual_nm: float
    tt_jitter_mas: float
    window_strehls: list[float] = field(default_factory=list)  # the paired evaluation's windows, in order
    sensitivity: float | None = None  # the paired evaluation's k in its windows
    settled: FrozenK | None = None  # with OGTL: what the evaluation's own OGTL settled to

    def to_dict(self) -> dict:
        return {**self.__dict__, "settled": None if self.settled is None else asdict(self.settled)}


@dataclass(frozen=True)
class FrozenK:
    """k and the NCPA offsets' state (in force, OGTL's scale of them) of a loop whose OGTL has
    settled: what both of the paired evaluation's loops run their windows at (``evaluate``)."""

    k: float
    offsets: bool
    offset_scale: float = 1.0

    @classmethod
    def of(cls, rtc: RtcParameters) -> FrozenK:
        return cls(rtc.sensitivity, rtc.slope_offset is not None, rtc.offset_scale)

    def set(self, rtc: RtcParameters) -> None:
        rtc.set_sensitivity(self.k)
        if self.offsets:
            rtc.apply_slope_offset()
        else:
            rtc.hold_slope_offset()
        rtc.scale_slope_offset(self.offset_scale)


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
    diverged_in: str = "run"  # or "evaluation": the paired evaluation's loop (``evaluate``), frame counted from its start
    safety_events: int = 0  # times the safety net restored the last good gains and k
    seconds: float = 0.0
    phases: dict = field(default_factory=dict)  # name -> (first frame, end frame)
    during_run: dict = field(default_factory=dict)  # "before"/"after" -> PhaseMetrics of the run's own phases
    sensitivities: tuple[float, float] = (1.0, 1.0)  # k at the end of *before* and at the end of the run
    coupling: CouplingStability | None = None  # a mis-registered loop's stability with the optimised gains
    offsets: tuple[bool, bool] = (False, False)  # NCPA offsets in force then (OGTL applies them)
    held: str | None = None  # why the optimiser did not run (the initial gains kept), None if it ran

    def failure(self) -> str | None:
        """Why the optimisation failed (exit status 3, no gain file): the loop diverged, its
        final gains leave a mis-registered loop lost (``coupling``), or the safety net could not
        recover it; None if none of these."""
        if self.diverged_at is not None:
            return f"the loop diverged at frame {self.diverged_at}" + (" (paired evaluation)" if self.diverged_in == "evaluation" else "")
        c = self.coupling
        if c is not None and not c.stable:
            return f"the optimised gains leave the mis-registered loop lost: {c.unstable_text()}"
        return could_not_recover(self.loop.telemetry)

    def strehl_difference(self) -> tuple[float, float | None]:
        """after - before of the paired evaluation: the mean over its windows and the standard
        error of that mean (None with one window)."""
        if self.before is None or self.after is None:
            return math.nan, None
        d = np.subtract(self.after.window_strehls, self.before.window_strehls)
        return float(d.mean()), (float(d.std(ddof=1) / math.sqrt(d.size)) if d.size > 1 else None)


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


MODEL_SEGMENT = 8192  # frequency grid of the model PSD: fine enough for the lowest cut-offs (0.1 Hz at 1700 Hz)


def initial_gains(
    gains: LoopGains,
    request: RunRequest,
    calibration: Calibration,
    cache: ArrayCache,
    loop: ClosedLoop,
    chi: np.ndarray,
    noise: np.ndarray,
    ogtl: bool,
    probe_mode: int,
) -> np.ndarray:
    """The optimisers' starting gains from the operating point: the run's gains capped for
    stability (``capped_gains``) at the larger of each mode's chi in the plant model and its
    chi at the worst seeing (with OGTL, gamma_i / gamma_probe grows as the correction degrades:
    the low orders lose less optical gain than the probed mode), and by ``noise_aware_gains``,
    MGM's optimum on a model of the loop's POL PSD: the turbulence of each mode at the run's
    seeing, L0 and wind, the vibrations on Tip/Tilt, and the WFS noise of the operating point
    (``noise``, ``sensor.modal_noise_nm``) over the optical gains the model expects at the
    run's seeing, for Tip/Tilt and the modes whose noise dominates.  A bright star keeps the
    design gains (lower gains there risk losing the PWFS's lock on a large low-order
    excursion); a faint one starts at the gains its noise allows, so that OGTL raising k
    towards chi = 1 cannot over-drive the noise.  With OGTL the model's optimum caps every
    mode: k of 3-5 turns the design gains of the turbulence-dominated modes into effective
    gains of ~0.7 at the faint end (R15.5, 1.0": "before" 0.03 against 0.12 so capped)."""
    obs = request.observation
    chi_worst = plant_model(calibration, cache, ogtl, probe_mode, ogtl_model.WORST_SEEING_ARCSEC)
    gamma = optical_gain_table(calibration, cache, request.seeing_arcsec)
    capped = capped_gains(
        gains.per_mode(len(chi)), obs, request.structure, np.maximum(chi, chi_worst), gains.forgetting, INITIAL_GAIN_FRACTION
    )
    atmosphere = request.atmosphere()
    model = noise_aware_gains(
        obs,
        request.structure,
        gains.forgetting,
        chi,
        calibration.basis.variance,
        atmosphere,
        noise / gamma,
        request.vibrations,
        1.0 / loop.mas_per_nm_tt,
        every_mode=ogtl,
    )
    return np.minimum(capped, model)


def noise_aware_gains(
    observation,
    structure,
    forgetting: float,
    chi: np.ndarray,
    basis_variance: np.ndarray,
    atmosphere: AtmosphereConfig,
    pol_noise_nm: np.ndarray,
    vibrations=None,
    nm_per_mas: float = 1.0,
    every_mode: bool = False,
) -> np.ndarray:
    """MGM's optimum (Eq. cost) on the model POL PSD for Tip/Tilt and each noise-dominated mode
    (inf for the others: they keep their design gains; ``every_mode``: the optimum for all),
    on a MODEL_SEGMENT grid, over the MGM range (margin included).  A mode is noise-dominated when its turbulence's variance is below
    the noise's (MGM's own rule, ``mgm.noise_dominated``).  The model: white noise of ``pol_noise_nm`` RMS per frame plus the
    turbulence - for Tip/Tilt the frozen-flow Tip/Tilt PSD (``TurbulenceTipTilt`` at the
    effective wind) and the vibrations' lines on that axis (Tip's on mode 1, Tilt's on mode 2;
    their mean on both put the lines' power where it is not: 9 and 6.5 mas at 13 Hz became 7.8
    on each), in nm through ``nm_per_mas``; for the other modes
    the layers' ``modal_psd`` weighted by their Cn^2 (basis variances in rad^2 at 500 nm for
    r0 = 1 m)."""
    rate = observation.frame_rate_hz
    n = len(chi)
    f = np.fft.rfftfreq(MODEL_SEGMENT, 1.0 / rate)[1:]
    unit, ba = unit_loops(observation, structure, forgetting, n)
    L1 = mgm.unit_open_loops(unit, chi, observation.delay_frames, rate, f, ba)
    upper = mgm.gain_limits(unit, chi, observation.delay_frames, rate, mgm.MgmSettings().margin, ba)
    nm2 = np.asarray(basis_variance[:n]) * atmosphere.r0_m ** (-5.0 / 3.0) * (LAMBDA_REF_M * 1e9 / (2 * math.pi)) ** 2
    modes = np.arange(1, n + 1)
    psd = np.repeat((np.asarray(pol_noise_nm) ** 2 / (rate / 2))[:, None], f.size, axis=1)
    for w, layer in zip(atmosphere.weights, atmosphere.layers):
        psd[2:] += modal_psd(f, w * nm2[2:], cutoff_hz(modes[2:], layer.wind_speed_m_s, LBT_DIAMETER_M))
    tt = TurbulenceTipTilt(atmosphere.seeing_arcsec, atmosphere.L0_m, atmosphere.effective_wind_speed_m_s).psd(f)
    for mode, axis in enumerate(("tip", "tilt")):  # mode 1 is Tip, mode 2 Tilt, each with its own lines
        psd[mode] += (tt if vibrations is None else tt + vibrations.psd(f, axis)) * nm_per_mas**2
    g = mgm.optimal_gains(psd, L1, upper)
    signal = np.sum(psd, axis=1) * (f[1] - f[0]) - np.asarray(pol_noise_nm) ** 2 * (f[-1] - f[0]) / (rate / 2)
    noisy = signal < np.asarray(pol_noise_nm) ** 2
    noisy[:2] = True  # Tip/Tilt: its model (turbulence and vibration lines) is trusted whatever its SNR
    return g if every_mode else np.where(noisy, g, np.inf)


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


def _new_loop(request: OptimizeRequest, cal: Calibration, gains: LoopGains, structure) -> ClosedLoop:
    """The run's closed loop at t = 0: same seed, same turbulence, vibrations and noise; its
    turbulence does not repeat within the session (``session_seconds``)."""
    return closed_loop_for(request.run, cal, gains, structure, duration_s=session_seconds(request))


def session_seconds(request: OptimizeRequest) -> float:
    """An upper bound of the simulated time of an optimisation (closing and one period,
    OGTL's settling at most, *before* and *after*, the optimisation: the longer of MGM's
    duration and twice every trial sequence of the three groups and one more, the most
    ``_run_optimiser`` runs).  The same for either method, so that the screens, sized for the
    session (``FrozenFlowAtmosphere``), are the same: MGM and trial-and-error on one seed see
    the same turbulence, and their results compare paired."""
    rate = request.run.observation.frame_rate_hz
    optimise = max(request.duration, 2 * request.sequence * (3 * (TRIAL_VALUES + 1) + 1))
    settle = OGTL_MAX_SETTLING_PERIODS * request.period if request.ogtl else 0.0
    closing = closing_frames(rate) / rate
    live = closing + request.period + settle + 2 * request.measure_s + optimise + EVALUATION_SETTLE_S
    return max(live, closing + evaluation_settle_s(request.period, request.ogtl) + request.windows * request.window)


def evaluation_settle_s(period_s: float, ogtl: bool) -> float:
    """The paired evaluation's settling after its closing: EVALUATION_SETTLE_S, and if the
    evaluation's loop runs OGTL (``ogtl``) at least OGTL_MAX_SETTLING_PERIODS of its updates
    (every ``period_s``), the run's longest settling (OGTL brings k from 1).  The same for both gain sets whatever
    their OGTL does, so that their windows are paired in time; the longest, so that each
    gain set is judged at the k its loop's OGTL reaches, not mid-way: settled for the run's
    own count (five updates where the run's settling ended on a hold), the faint R16.5 case's
    evaluations ended at k = 3.4 and 5.2, in twelve at 5.2 and 5.9, and *before* read 0.127
    where it reads 0.209 (docs/physics.md, "The paper's faint cases").  Decided by
    the evaluation's loop, not by the request: a diagnostic that evaluates an OGTL request at
    a fixed k settles as any fixed-k evaluation."""
    if not ogtl:
        return EVALUATION_SETTLE_S
    return max(EVALUATION_SETTLE_S, OGTL_MAX_SETTLING_PERIODS * period_s)


def evaluate(
    request: OptimizeRequest,
    cal: Calibration,
    design: LoopGains,
    gains: np.ndarray,
    k: float,
    offsets: bool = False,
    progress=None,
    ogtl: OgtlTask | None = None,
    freeze: FrozenK | None = None,
) -> PhaseMetrics:
    """Metrics of ``gains`` on the run's own turbulence and noise: a loop closed afresh from
    t = 0 at k = 1 (``closing_frames``, as the run), settled (``evaluation_settle_s``),
    measured over ``windows`` consecutive windows of ``window_s``.  Without ``ogtl`` k is then
    set and fixed, the NCPA offsets applied with it if ``offsets``; with it (a fresh task) the
    loop is closed much as the run closes it: OGTL from k = 1 (``k`` unused) for the run's
    longest settling (``evaluation_settle_s``; the run's closing is stretched to an update
    boundary, this one is not), applying the offsets itself.  k then belongs to the loop, not
    to the gains: a k the run reached on other turbulence is not imposed, nor is k raised at
    once on a loop still converging (docs/physics.md, "Over the magnitudes").  OGTL then stops
    (its probe stays on) and the windows run at one k: the loop's own (``settled``), or
    ``freeze`` (*before*'s, for *after*: ``evaluate_pair``).  The Strehl ratio is the mean of
    the windows' (each a long exposure); residual and jitter are over all of them.  *before*
    and *after* so measured differ by the gains alone - a paired comparison: measured in the
    run's own phases, 0.5 s apart in time, they differ by the turbulence too, by up to +-0.05
    in Strehl at 1.0" (docs/physics.md).  Paired, one window still depends on what the
    turbulence does in it: at R17.5-18.5, 0.6" the difference of two gain sets moves by
    0.02-0.04 from one 1 s window to the next, hence several windows and the standard error of
    their paired differences (``OptimizeResult.strehl_difference``).  Raises LoopDiverged."""
    loop = settled_evaluation_loop(request, cal, design, gains, k, offsets, progress, ogtl)
    settled = None
    if ogtl is not None:
        loop.remove_aux_loop(ogtl)
        settled = FrozenK.of(loop.rtc_parameters)
        (freeze or settled).set(loop.rtc_parameters)
    n_window = request.frames(request.window)
    skip = min(n_window // 2, request.frames(0.05))
    wavelength = band_wavelength(request.run.band)
    start, strehls = loop.frame, []
    for i in range(request.windows):
        psf = loop.psf_accumulator(wavelength)
        loop.run(n_window, psf=psf, skip=skip if i == 0 else 0, progress=progress)
        strehls.append(psf.strehl)
    metrics = _phase_metrics(loop, float(np.mean(strehls)), start + skip, loop.frame)
    metrics.window_strehls = strehls
    metrics.sensitivity = loop.rtc_parameters.sensitivity
    metrics.settled = settled
    return metrics


def settled_evaluation_loop(
    request: OptimizeRequest,
    cal: Calibration,
    design: LoopGains,
    gains: np.ndarray,
    k: float,
    offsets: bool = False,
    progress=None,
    ogtl: OgtlTask | None = None,
) -> ClosedLoop:
    """``evaluate``'s loop before its measurement: closed afresh at k = 1 on the run's own
    turbulence and noise, then either k set and the NCPA offsets applied if ``offsets``, or
    ``ogtl`` started from k = 1 (it applies them once k is calibrated); settled for
    ``evaluation_settle_s``.  Raises LoopDiverged."""
    r = request.run
    loop = _new_loop(request, cal, design, r.sampled_structure())
    loop.set_gains(gains)
    loop.rtc_parameters.hold_slope_offset()  # NCPA offsets once k is set, as OGTL applies them
    loop.run(closing_frames(r.observation.frame_rate_hz), progress=progress)
    if ogtl is not None:
        loop.add_aux_loop(ogtl)
    else:
        loop.rtc_parameters.set_sensitivity(k)
        if offsets:
            loop.rtc_parameters.apply_slope_offset()
    loop.run(request.frames(evaluation_settle_s(request.period, ogtl is not None)), progress=progress)
    return loop


def _phase_metrics(loop: ClosedLoop, strehl: float, start: int, stop: int) -> PhaseMetrics:
    tm = loop.telemetry
    rms = np.asarray(tm.residual_rms_nm[start:stop])
    tt = tm.series("residual_tt")[start:stop] * loop.mas_per_nm_tt
    return PhaseMetrics(strehl, float(np.sqrt(np.mean(rms**2))), float(np.sqrt(np.mean(tt.var(axis=0)))))


def _settled(records: list[dict]) -> bool:
    """OGTL's k has settled: its last update had an estimate and moved k by its own rule (not
    held for a low probe SNR, for want of one or while the commands grow) and moved log k by
    less than SETTLED_LOG_STEP.  A held update says nothing of where k goes: read as settled,
    one held for the SNR ended R16.5's settling at k = 3.4 of ~4.5 and the paired evaluation
    judged MGM's gains mid-transient (0.077 -> 0.047); one held while the commands grew ended
    R15.5, 1.5"'s at k = 2.25 of the ~10 its evaluations reach in their twelve updates, and
    trial-and-error, scanning at a quarter of that k, kept 3x the initial gain of modes 3-120,
    which diverged in the evaluation (docs/physics.md).  A bound still ends it."""
    if not records or records[-1]["status"] in ogtl_model.HELD:
        return False
    previous = records[-2]["sensitivity"] if len(records) > 1 else 1.0
    return abs(math.log(records[-1]["sensitivity"] / previous)) < SETTLED_LOG_STEP


def _optimiser(
    request: OptimizeRequest,
    calibration: Calibration,
    cache: ArrayCache,
    chi: np.ndarray,
    forgetting: float,
    ogtl: OgtlTask | None,
    initial: np.ndarray,
) -> tuple[MgmTask | TrialAndErrorTask, int]:
    """The optimisation phase's task and its length in frames.  Trial-and-error scans each
    group's initial gain too, and keeps it unless a scanned gain does significantly better."""
    obs = request.run.observation
    if request.method == "mgm":
        machine = mgm_machine(obs, request.run.structure, chi, request.settings_for_rate(obs.frame_rate_hz), forgetting)
        return MgmTask(request.frames(request.period), machine, ogtl), request.frames(request.duration)
    sequence = request.frames(request.sequence)
    settle = max(1, sequence // 5)
    incumbents = [float(np.mean(initial[modes])) for _, modes in gain_groups(len(chi))]
    trial = TrialAndErrorTask(
        calibration.basis.n_modes, trial_scans(request, chi, initial), settle, sequence - settle, incumbents, trial_shapes(initial)
    )
    # one sequence more: the task starts on an update boundary of OGTL's period, its first
    # update after a partial sequence waits for the next (``TrialAndErrorTask.update``)
    return trial, sequence * (sum(len(order) for order in trial.orders) + 1)


def _run_optimiser(loop: ClosedLoop, optimiser: MgmTask | TrialAndErrorTask, frames: int, tick) -> None:
    """MGM for ``frames``; trial-and-error until its scan is done: a sequence that OGTL's k
    changed part-way is run again (``TrialAndErrorTask.update``), so the scan may take a few
    sequences more than ``frames``; at most twice as long."""
    if isinstance(optimiser, MgmTask):
        loop.run(frames, progress=tick)
        return
    ran = 0
    while not optimiser.done and ran < 2 * frames:
        loop.run(optimiser.period_frames, progress=tick)
        ran += optimiser.period_frames


@dataclass
class _Session:
    """What the live phases of one optimisation work with (``optimize``)."""

    loop: ClosedLoop
    aux: list  # OGTL (when on) and the live metrics, from the settling phase on
    optimiser: MgmTask | TrialAndErrorTask
    ogtl: OgtlTask | None  # the run's OGTL task (also in ``aux``), None without OGTL
    n_opt: int  # frames of the optimisation phase
    net: SafetyNet
    period: int  # frames per update
    frames: dict  # closing, settle (at most), measure, skip
    new_ogtl: Callable[[], OgtlTask | None]  # a fresh OGTL task like the run's (None without OGTL), for the evaluation


def _session(request: OptimizeRequest, cal: Calibration, cache: ArrayCache, gains: LoopGains, chi: np.ndarray) -> _Session:
    """The loop at its initial gains and the tasks beside it; the phases' lengths in frames:
    closing is stretched so that *before* ends on an update boundary (the optimiser starts with
    OGTL's updates and MGM's windows are whole periods: tasks run when frame % period == 0)."""
    r = request.run
    obs = r.observation
    loop = _new_loop(request, cal, gains, r.sampled_structure())
    if request.ogtl:
        loop.rtc_parameters.hold_slope_offset()  # OGTL applies the NCPA offsets once k is calibrated
    noise = loop.sensor.modal_noise_nm(cal.reconstructor)
    loop.set_gains(initial_gains(gains, r, cal, cache, loop, chi, noise, request.ogtl, request.ogtl_settings.mode))
    period = request.frames(request.period)
    ogtl = request_ogtl_task(request, cal, cache, noise)
    optimiser, n_opt = _optimiser(request, cal, cache, chi, gains.forgetting, ogtl, loop.rtc_parameters.gains)
    aux: list = [ogtl] if ogtl is not None else []
    gamma = optical_gain_table(cal, cache, request.chi_seeing)
    aux.append(LiveMetricsTask(period, gamma, band_wavelength(r.band), obs.magnitude_r, loop.sensor.photons_per_frame))
    n_measure = request.frames(request.measure_s)
    n_settle = OGTL_MAX_SETTLING_PERIODS * period if request.ogtl else 0  # at most
    n_close = closing_frames(obs.frame_rate_hz)
    n_close += (-(n_close + n_settle + n_measure)) % period
    skip = min(n_measure // 2, request.frames(0.05))  # of each measurement, PSF and metrics alike
    frames = {"closing": n_close, "settle": n_settle, "measure": n_measure, "skip": skip}

    net = safety_net(obs.frame_rate_hz, aux + [optimiser])
    return _Session(loop, aux, optimiser, ogtl, n_opt, net, period, frames, lambda: request_ogtl_task(request, cal, cache, noise))


def _measure(loop: ClosedLoop, s: _Session, wavelength: float, tick) -> tuple[PhaseMetrics, tuple[int, int]]:
    """A measurement phase in the run: its metrics and its frames."""
    psf = loop.psf_accumulator(wavelength)
    start, skip = loop.frame, s.frames["skip"]
    loop.run(s.frames["measure"], psf=psf, skip=skip, progress=tick)
    return _phase_metrics(loop, psf.strehl, start + skip, loop.frame), (start, loop.frame)


def _live_phases(s: _Session, result: OptimizeResult, wavelength: float, tick) -> None:
    """Closing, OGTL's settling, *before*, the optimisation, *after*, in the run's own loop."""
    loop = s.loop
    loop.run(s.frames["closing"], progress=tick)
    result.phases["closing"] = (0, loop.frame)
    for task in s.aux + [s.net]:
        loop.add_aux_loop(task)
    if s.frames["settle"]:
        for i in range(OGTL_MAX_SETTLING_PERIODS):
            loop.run(s.period, progress=tick)
            if i + 1 >= OGTL_SETTLING_PERIODS and _settled(loop.telemetry.aux["ogtl"]):
                break
        result.phases["settling"] = (result.phases["closing"][1], loop.frame)
    result.during_run["before"], result.phases["before"] = _measure(loop, s, wavelength, tick)
    k_before, offsets_before = loop.rtc_parameters.sensitivity, loop.rtc_parameters.slope_offset is not None
    start = loop.frame
    if s.ogtl is not None and not s.ogtl.calibrated:
        # gains tuned at a k OGTL has not calibrated are over-driven when it does (``MgmTask``)
        result.held = UNCALIBRATED_K
        loop.run(s.n_opt, progress=tick)
    else:
        loop.remove_aux_loop(s.net)  # the net acts after the optimiser in an update
        loop.add_aux_loop(s.optimiser)
        loop.add_aux_loop(s.net)
        _run_optimiser(loop, s.optimiser, s.n_opt, tick)
        loop.remove_aux_loop(s.optimiser)
    result.phases["optimisation"] = (start, loop.frame)
    result.gains = loop.rtc_parameters.gains
    result.during_run["after"], result.phases["after"] = _measure(loop, s, wavelength, tick)
    result.sensitivities = (k_before, loop.rtc_parameters.sensitivity)
    result.offsets = (offsets_before, loop.rtc_parameters.slope_offset is not None)


def evaluate_pair(
    request: OptimizeRequest,
    cal: Calibration,
    design: LoopGains,
    result: OptimizeResult,
    new_ogtl: Callable[[], OgtlTask | None],
    tick=None,
) -> None:
    """*before* and *after* of ``result``: the initial and the optimised gains in the paired
    evaluation (``evaluate``).  With OGTL (a fresh task from ``new_ogtl`` for each) both loops
    close much as the run's: OGTL from k = 1 settling for the run's longest settling
    (``evaluation_settle_s``), the closing not stretched to an update boundary, and both then
    measure their windows at the k (and offsets) *before*'s OGTL settled to; without, both at
    the fixed k and NCPA offsets of the end of *before*.  Judged so, an optimiser that returns
    the initial gains scores exactly zero, whatever k did while it ran.  Why one k: with OGTL
    running through the windows the two loops' k paths part, and the windows differ by them as
    much as by the gains - R14.5 1.5" seed 2: *after*'s OGTL held at k = 5.06 against
    *before*'s 8.41, -0.049, where at one k both gain sets read 0.0731; R16.5 0.6" seed 2: k
    2.31 and 2.40 at the end, -0.016 +- 0.004, at one k +0.002 (docs/physics.md, "Over the
    magnitudes")."""
    k, offsets = result.sensitivities[0], result.offsets[0]
    try:
        result.before = evaluate(request, cal, design, result.initial_gains, k, offsets, tick, new_ogtl())
        result.after = evaluate(request, cal, design, result.gains, k, offsets, tick, new_ogtl(), result.before.settled)
    except LoopDiverged as e:
        result.diverged_at, result.diverged_in = e.frame, "evaluation"


def optimize(
    request: OptimizeRequest, cache: ArrayCache = ArrayCache(None), progress=None, calibration: Calibration | None = None
) -> OptimizeResult:
    """Run the phases (see the module docstring), then evaluate the initial and the final gains
    paired (``evaluate``).  ``progress(done, total)`` per frame; ``calibration``: the
    request's, already computed."""
    r = request.run
    obs = r.observation
    structure = r.sampled_structure()
    gains = r.design_gains()
    if not r.allow_unstable:
        check_stability(obs, gains, structure)
    cal = calibration or calibration_for(r, cache)
    chi = plant_model(cal, cache, request.ogtl, request.ogtl_settings.mode, request.chi_seeing)
    s = _session(request, cal, cache, gains, chi)
    f = s.frames
    n_window = request.frames(request.window)
    settle = request.frames(evaluation_settle_s(request.period, request.ogtl))
    n_evaluation = 2 * (closing_frames(obs.frame_rate_hz) + settle + request.windows * n_window)
    total = f["closing"] + f["settle"] + 2 * f["measure"] + s.n_opt + n_evaluation
    done = 0

    def tick(_):
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, total)

    initial = s.loop.rtc_parameters.gains
    result = OptimizeResult(request, initial, initial, None, None, s.loop, chi)
    t0 = time.perf_counter()
    try:
        _live_phases(s, result, band_wavelength(r.band), tick)
    except LoopDiverged as e:
        result.diverged_at = e.frame
        result.gains = s.loop.rtc_parameters.gains
    if result.diverged_at is None:
        evaluate_pair(request, cal, gains, result, s.new_ogtl, tick)
    result.safety_events = s.net.events
    if result.diverged_at is None:
        result.coupling = registration_stability(r, cal, s.loop, gains.forgetting, structure, cache)
    result.seconds = time.perf_counter() - t0
    return result
