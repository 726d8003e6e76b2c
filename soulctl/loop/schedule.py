"""The gain optimisation's request and schedule: ``OptimizeRequest`` (method, periods,
durations, windows) and the rules that size them from the frame rate: the update period
(``default_period_s``), MGM's Welch segment (``resolving_segment``, ``welch_settings``), the
optimisation's duration and trial-and-error's sequences.  ``loop.optimize`` runs it."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from .. import defaults
from ..control import mgm
from ..control.delay import fractional_taps
from ..control.ogtl import OgtlSettings
from ..errors import InputError
from ..ranges import EVALUATION_WINDOWS, MEASURE_S, MIN_MEASURE_FRAMES, OPTIMISATION_S, PERIOD_S, PROBE_MIN_CYCLES, SEQUENCE_S
from .run import RunRequest, closing_frames

METHODS = ("trial", "mgm")
MIN_SEGMENT = 64  # frames: the shortest Welch segment MGM accepts ...
MAX_SEGMENT = 512  # ... and the longest it takes from a window
MGM_RESOLUTION_HZ = 1.0  # the default period holds 4 segments with bins at most this wide (``resolving_segment``)
DEFAULT_DURATION_S = 5.0  # MGM's default optimisation phase: at least this ...
DEFAULT_UPDATES = 5  # ... and this many update periods
MIN_SEQUENCE = 10  # frames of one trial-and-error sequence (a fifth of them settling)
DEFAULT_SEQUENCE_S = 0.25  # the default trial-and-error sequence, at least DEFAULT_SEQUENCE_FRAMES
DEFAULT_SEQUENCE_FRAMES = 100
DEFAULT_PERIOD_S = 1.0  # the shortest default update period (``default_period_s``)
OGTL_SETTLING_PERIODS = 4  # OGTL updates before the "before" measurement, at least ...
OGTL_MAX_SETTLING_PERIODS = 12  # ... and at most, until k has settled (``_settled``)
SETTLED_LOG_STEP = 0.1  # k has settled when its last update, a measured one, changed log k by less than this
OPTIMISER_OGTL = True  # `optimize gains` and a sweep's optimised cases run OGTL unless told not to
# The paired evaluation's settling at k after the closing (``evaluate``): a steady state for any
# gains the optimisers return.  Measured at R16.5, 1.0", 250 Hz: MGM's gains (lower on Tip and the
# noise-dominated modes) close from the open loop in ~0.6 s, the initial gains in ~0.2 s; with
# 0.2 s the evaluation measured MGM's gains mid-transient (Strehl 0.129 -> 0.111), with 1 s in
# the steady state (0.127 -> 0.152; over 1-3 s the residual is 386 against 401 nm).
EVALUATION_SETTLE_S = 1.0
TRIAL_VALUES = 8  # gains per group


@dataclass(frozen=True, kw_only=True)
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
