"""The paired evaluation of gains (``evaluate``): a loop closed afresh on the run's own
turbulence and noise, OGTL settling k, then windows at a frozen k (``FrozenK``), so that two
gain sets differ by the gains alone (``loop.optimize``, phase 4)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from ..control.gains import (
    LoopGains,
)
from ..optics.calibration import Calibration
from .auxloop import RtcParameters
from .auxloops import OgtlTask
from .metrics import band_wavelength
from .run import closed_loop_for, closing_frames
from .schedule import OptimizeRequest, evaluation_settle_s, session_seconds
from .simulation import ClosedLoop


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


def _new_loop(request: OptimizeRequest, cal: Calibration, gains: LoopGains, structure) -> ClosedLoop:
    """The run's closed loop at t = 0: same seed, same turbulence, vibrations and noise; its
    turbulence does not repeat within the session (``session_seconds``)."""
    return closed_loop_for(request.run, cal, gains, structure, duration_s=session_seconds(request))


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
