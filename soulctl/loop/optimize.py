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
from dataclasses import dataclass, field

import numpy as np

from ..control import ogtl as ogtl_model
from ..control.coupling import CouplingStability
from ..control.gains import (
    LoopGains,
    check_stability,
    gain_groups,
)
from ..optics.cache import ArrayCache
from ..optics.calibration import Calibration
from .auxloops import LiveMetricsTask, MgmTask, OgtlTask, SafetyNet, TrialAndErrorTask, could_not_recover
from .chi_model import optical_gain_table, plant_model
from .evaluation import PhaseMetrics, _new_loop, _phase_metrics, evaluate
from .gain_policy import initial_gains
from .metrics import band_wavelength
from .optimisers import mgm_machine, request_ogtl_task, safety_net, trial_scans, trial_shapes
from .run import calibration_for, closing_frames, registration_stability
from .schedule import OGTL_MAX_SETTLING_PERIODS, OGTL_SETTLING_PERIODS, SETTLED_LOG_STEP, OptimizeRequest, evaluation_settle_s
from .simulation import ClosedLoop, LoopDiverged

# An optimiser with OGTL starts only once OGTL has a calibrated k (``OgtlTask.calibrated``); the
# result's ``held`` when its settling and *before* ended without one:
UNCALIBRATED_K = "OGTL had acted on no reliable probe estimate when the optimiser was to start: k uncalibrated, the initial gains kept"


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
