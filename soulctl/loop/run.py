"""One `loop run`: calibrate (cached), close the loop for a duration, and reduce the telemetry
to what SOUL would deliver (Strehl, jitter, residuals, rejection, spectra)."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from .. import defaults
from ..control.coupling import CouplingStability, registration_verdict
from ..control.filters import coefficient_rows
from ..control.gains import LoopGains, check_stability, design_gains, unit_loops
from ..control.ogtl import OFFSETS_CHI_TOLERANCE
from ..control.structure import StructuralResonance, sampled_structure
from ..control.transfer import VIBRATION_HZ
from ..disturbance.vibrations import VibrationSpectrum
from ..observation import Observation
from ..optics.asm import DEFAULT_INFLUENCE, AsmGeometry, check_influence
from ..optics.atmosphere import AtmosphereConfig, Layer
from ..optics.cache import ArrayCache
from ..optics.calibration import BasisSetup, Calibration, CalibrationSetup, calibrate, check_sampling, moved_mirror_response
from ..optics.calibration_noise import CalibrationNoise, measured_calibration
from ..optics.ncpa import NcpaSpec, non_common_path
from ..optics.pwfs import PyramidConfig
from ..optics.registration import Misregistration
from ..ranges import DURATION_S, OUTER_SCALE_M, OVERSAMPLING, SEED, SEEING_ARCSEC, WFS_FIELD_OF_VIEW_ARCSEC, WIND_M_S
from ..telemetry.figures import JITTER_EDGE_HZ, pseudo_open_loop, rejection, tip_tilt_jitter
from ..telemetry.recorder import Sink, TelemetryRecorder
from ..telemetry.schema import LBT_SYSTEM
from .auxloops import could_not_recover
from .chi_model import optical_gain_table
from .metrics import LoopMetrics, PsfAccumulator, band_wavelength
from .simulation import ClosedLoop, LoopDiverged

CLOSING_S = 0.1  # the loop closes at k = 1 before auxiliary loops start ...
MIN_CLOSING_FRAMES = 50  # ... for at least this many frames
SETTLING_S = 0.02  # left out of the metrics while the loop settles (at least) ...
SETTLING_FRAMES = 10  # ... and at least these frames (~3/g at the paper's gains, g >= 0.3)
CLOSED_LOOP_FIGURES = ("strehl", "tt_jitter_mas", "tt_jitter_pol_mas", "tt_jitter_pol_3hz_mas", "residual_nm", "rejection_13hz")


@dataclass(frozen=True, kw_only=True)
class RunRequest:
    """What ``run`` needs, resolved: built by ``soulctl.run_config.RunConfig.request`` (the
    run description's one factory) or directly by the Python API.

    Parameters
    ----------
    observation : Observation
        The star's set-up: binning, modes, frame rate, Tip/Tilt controller, delay.
    seeing_arcsec, wind_m_s, L0_m : float
        Seeing at 500 nm (arcsec), effective wind of the LBT profile (m/s), outer scale (m).
    duration_s : float
        Simulated time (s).
    gains : LoopGains or None
        The gains the run starts from; None: ``control.gains.design_gains``.
    band : str
        Science band of the Strehl ratio (``loop.metrics.BANDS``).
    seed : int
        Seed of every random draw of the run (turbulence, noise, vibrations).
    noise : bool
        Detector noise on.
    vibrations : VibrationSpectrum or None
        Tip/Tilt vibration lines; None: none.
    oversampling : int
        Simulation pixels per binning-1 detector pixel.
    structure : StructuralResonance or None
        The adaptive secondary's 127 Hz resonance; None: none.
    allow_unstable : bool
        Run gains the stability check refuses.
    layers : tuple of Layer or None
        Explicit turbulence layers; None: the LBT profile at ``wind_m_s``.
    misregistration : Misregistration or None
        The mirror on the pyramid against the calibration; None: as calibrated.
    ncpa : NcpaSpec or None
        The science path's static aberration; None: none.
    calibration_noise : CalibrationNoise or None
        The interaction matrix measured at a finite flux; None: noiseless.
    influence : str
        The mirror's influence-function model (``optics.asm.INFLUENCES``).
    wfs_field_arcsec : float
        The pyramid's simulated field (a diameter, arcsec); 0: as sampled, no stop.
    """

    observation: Observation
    seeing_arcsec: float = defaults.SEEING_ARCSEC
    wind_m_s: float = defaults.WIND_M_S
    L0_m: float = defaults.L0_M
    duration_s: float = defaults.DURATION_S
    gains: LoopGains | None = None  # None: control.gains.design_gains
    band: str = defaults.BAND
    seed: int = defaults.SEED
    noise: bool = True
    vibrations: VibrationSpectrum | None = field(default_factory=VibrationSpectrum.lbt_default)
    oversampling: int = defaults.OVERSAMPLING
    structure: StructuralResonance | None = field(default_factory=StructuralResonance)
    allow_unstable: bool = False
    layers: tuple[Layer, ...] | None = None  # explicit turbulence layers; None: the LBT profile at wind_m_s
    misregistration: Misregistration | None = None  # the mirror on the pyramid against the calibration; None: as calibrated
    ncpa: NcpaSpec | None = None  # the science path's static aberration; None: none
    calibration_noise: CalibrationNoise | None = None  # the loop's D measured at a finite flux; None: noiseless
    influence: str = DEFAULT_INFLUENCE  # the mirror's influence-function model (``optics.asm``)
    wfs_field_arcsec: float = defaults.WFS_FIELD_ARCSEC  # the pyramid's simulated field (``PyramidConfig``); 0: as sampled, no stop

    def __post_init__(self):
        DURATION_S.check(self.duration_s, "duration")
        SEEING_ARCSEC.check(self.seeing_arcsec, "seeing")
        WIND_M_S.check(self.wind_m_s, "wind")
        OUTER_SCALE_M.check(self.L0_m, "L0")
        SEED.check(self.seed, "seed")
        OVERSAMPLING.check(self.oversampling, "oversampling")
        band_wavelength(self.band)
        check_sampling(self.observation.modes, self.oversampling)
        check_influence(self.influence)
        WFS_FIELD_OF_VIEW_ARCSEC.check(self.wfs_field_arcsec, "WFS field of view")

    def sampled_structure(self) -> StructuralResonance | None:
        """The structural resonance as the frame rate samples it (None above Nyquist)."""
        return sampled_structure(self.structure, self.observation.frame_rate_hz)

    def design_gains(self) -> LoopGains:
        """The gains the run starts from (``control.gains.design_gains``)."""
        return design_gains(self.observation, self.structure, self.gains)

    @property
    def frames(self) -> int:
        return max(1, round(self.duration_s * self.observation.frame_rate_hz))

    def atmosphere(self) -> AtmosphereConfig:
        """The turbulence: the explicit layers, else the LBT profile scaled to ``wind_m_s``."""
        if self.layers:
            return AtmosphereConfig(self.seeing_arcsec, self.L0_m, self.layers)
        return AtmosphereConfig.lbt_default(self.seeing_arcsec, self.L0_m, self.wind_m_s)

    @property
    def settling_frames(self) -> int:
        """The loop's settling allowance: 0.02 s, at least SETTLING_FRAMES."""
        return max(SETTLING_FRAMES, round(SETTLING_S * self.observation.frame_rate_hz))

    @property
    def skip(self) -> int:
        """Frames left out of the metrics while the loop closes: 20 % of the run, at least the
        settling allowance, at most half (a run shorter than twice the allowance has no
        closed-loop figures)."""
        return min(self.frames // 2, max(self.settling_frames, self.frames // 5))


def closing_frames(rate_hz: float) -> int:
    """Frames the loop runs at k = 1, without auxiliary loops, before they start."""
    return max(MIN_CLOSING_FRAMES, round(CLOSING_S * rate_hz))


@dataclass
class RunResult:
    request: RunRequest
    gains: LoopGains
    calibration: Calibration
    telemetry: TelemetryRecorder
    metrics: LoopMetrics | None
    psf: np.ndarray | None
    diverged_at: int | None
    diverged_residual_nm: float | None
    seconds: float
    calibration_seconds: float
    mas_per_nm: float
    spectra: dict = field(default_factory=dict)
    final_gains: np.ndarray | None = None  # per mode, at the end (auxiliary loops may change them)
    final_sensitivity: float = 1.0  # the slope sensitivity k at the end
    notes: tuple[str, ...] = ()  # what the run changed of the request, and why (e.g. vibration lines dropped)
    coupling: CouplingStability | None = None  # the mis-registered loop's stability (None: registered)

    def configuration(self) -> dict:
        return run_configuration(self.request, self.gains)

    def failure(self) -> str | None:
        """Why the run failed (exit status 3): the loop diverged, a mis-registration left it
        lost (``coupling``), or the safety net of its auxiliary loops could not recover it;
        None if none of these."""
        if self.diverged_at is not None:
            return f"loop diverged at frame {self.diverged_at} (residual {self.diverged_residual_nm:.0f} nm RMS)"
        c = self.coupling
        if c is not None and not c.stable:
            return (
                f"the loop is lost: with this mis-registration {c.unstable_text()}; "
                f"they grow until the pyramid saturates (Strehl {self._strehl_text()})"
            )
        return could_not_recover(self.telemetry)

    def _strehl_text(self) -> str:
        return "n/a" if self.metrics is None or self.metrics.strehl is None else f"{self.metrics.strehl:.3f}"


def run_configuration(r: RunRequest, gains: LoopGains) -> dict:
    """The run's configuration as telemetry files store it (JSON)."""
    return {
        "observation": r.observation.to_dict(),
        "seeing_arcsec": r.seeing_arcsec,
        "wind_m_s": r.wind_m_s,
        "L0_m": r.L0_m,
        "duration_s": r.duration_s,
        "frames": r.frames,
        "skipped_frames": r.skip,
        "band": r.band,
        "seed": r.seed,
        "noise": r.noise,
        "oversampling": r.oversampling,
        "field_of_view_arcsec": r.wfs_field_arcsec,
        "gains": asdict(gains),
        "vibrations": [asdict(line) for line in r.vibrations.lines] if r.vibrations else [],
        "structure": asdict(r.structure) if r.structure else None,
    }


def _metrics(request: RunRequest, tm: TelemetryRecorder, psf: PsfAccumulator, mas_per_nm: float) -> tuple[LoopMetrics, dict]:
    """The figures of ``LoopMetrics`` over the run's window (``telemetry.figures``: the same
    functions `telemetry psd` calls on the run's record, which stores the Tip/Tilt scale of
    the run's pupil) and the jitter spectra of the plots."""
    obs = request.observation
    skip, rate = request.skip, obs.frame_rate_hz
    scale = 1.0 / mas_per_nm
    residual = tm.series("residual_tt")[skip:]
    pol = pseudo_open_loop(tm.series("measured_tt"), tm.series("command_tt"), obs.delay_frames)[skip:]
    n = len(residual)
    missing: dict[str, str] = {}
    if skip < request.settling_frames:
        missing = dict.fromkeys(CLOSED_LOOP_FIGURES, f"loop not settled: the run needs at least {2 * request.settling_frames / rate:.2g} s")
    jitter_res, jitter_pol = tip_tilt_jitter(residual, rate, scale), tip_tilt_jitter(pol, rate, scale)
    rej, why = rejection(residual, pol, rate, VIBRATION_HZ)
    pol_band = jitter_pol.above() if jitter_pol is not None else None
    for name, value, why_not in (
        ("tt_jitter_mas", jitter_res, "run too short"),
        ("tt_jitter_pol_mas", jitter_pol, "run too short"),
        ("tt_jitter_pol_3hz_mas", pol_band, f"run too short to resolve {JITTER_EDGE_HZ:g} Hz"),
        ("rejection_13hz", rej, why),
    ):
        if value is None:
            missing.setdefault(name, why_not or "run too short")

    def unless_missing(name, value):
        return None if name in missing else value

    m = LoopMetrics(
        band=request.band,
        strehl=unless_missing("strehl", psf.strehl if psf.frames else None),
        tt_jitter_mas=unless_missing("tt_jitter_mas", jitter_res.total if jitter_res else None),
        tt_jitter_pol_mas=unless_missing("tt_jitter_pol_mas", jitter_pol.total if jitter_pol else None),
        tt_jitter_pol_3hz_mas=unless_missing("tt_jitter_pol_3hz_mas", pol_band),
        residual_nm=unless_missing("residual_nm", float(np.sqrt(np.mean(tm.residual_rms_nm[skip:] ** 2))) if n else None),
        rejection_13hz=unless_missing("rejection_13hz", rej),
        frames=tm.frames,
        skipped_frames=skip,
        jitter_resolution_hz=jitter_pol.resolution_hz if jitter_pol else None,
        not_available=missing,
    )
    spectra: dict = {"modal_variance_nm2": tm.residual_moments.variance}
    if jitter_res is not None and jitter_pol is not None and "tt_jitter_mas" not in missing:
        spectra |= {"residual": jitter_res, "pseudo_open_loop": jitter_pol}
    return m, spectra


def calibration_setup(request: RunRequest) -> CalibrationSetup:
    """What the request's calibration depends on (binning, modulation, sampling, modes, the
    mirror's influence functions)."""
    obs = request.observation
    config = PyramidConfig(
        binning=obs.binning,
        modulation_lambda_over_d=obs.modulation_lambda_over_d,
        oversampling=request.oversampling,
        field_of_view_arcsec=request.wfs_field_arcsec,
    )
    return CalibrationSetup(config, obs.modes, BasisSetup(AsmGeometry(influence=request.influence)))


def calibration_for(request: RunRequest, cache: ArrayCache) -> Calibration:
    return calibrate(calibration_setup(request), cache)


def registration_stability(
    request: RunRequest, cal: Calibration, loop: ClosedLoop, forgetting: float, structure, cache: ArrayCache
) -> CouplingStability | None:
    """The loop's stability with the request's mis-registration (``control.coupling``) at the
    end of its run: Q = R D', R the loop's own reconstructor (the measured one with calibration
    noise), D' the moved mirror's response; the gains and slope sensitivity k in force then
    (what MGM and OGTL ended with), chi_i = k gamma_i with gamma_i the noiseless calibration's
    optical-gain table at the run's seeing (computed once per seeing, then cached); None when
    the mirror is where it was calibrated."""
    registration = request.misregistration
    if registration is None or registration.is_identity:
        return None
    obs = request.observation
    params = loop.rtc_parameters
    chi = params.sensitivity * optical_gain_table(cal, cache, request.seeing_arcsec)
    coupling = loop.calibration.reconstructor @ moved_mirror_response(cal, registration, cache)
    return registration_verdict(obs, structure, forgetting, coupling, np.asarray(params.gains) * chi, obs.delay_frames)


def _close_and_run(loop: ClosedLoop, request: RunRequest, psf: PsfAccumulator, n_close: int, tasks, progress) -> None:
    """The run's frames; with auxiliary loops (``tasks``), the loop closes at k = 1 for
    ``n_close`` frames before they start."""
    if tasks is not None:
        loop.run(n_close, psf=psf, skip=request.skip, progress=progress)
        for task in tasks:
            loop.add_aux_loop(task)
    loop.run(
        request.frames - n_close,
        psf=psf,
        skip=max(0, request.skip - n_close),
        progress=None if progress is None else (lambda k: progress(n_close + k)),
    )


def _prepare(loop: ClosedLoop, request: RunRequest, gains: LoopGains, cal: Calibration, cache, aux, sink):
    """The auxiliary loops of ``aux`` with their initial gains, and the sink's description:
    (frames the loop runs at k = 1 before the tasks start, the tasks, the gains it starts with)."""
    n_close, tasks = 0, None
    if aux is not None:
        if aux.ogtl:
            loop.rtc_parameters.hold_slope_offset()  # OGTL applies the NCPA offsets once k is calibrated
        tasks, initial = aux(request, gains, cal, cache, loop)
        loop.set_gains(initial)
        gains = LoopGains.from_modes(initial, gains.forgetting)  # what the loop started with
        n_close = min(request.frames, closing_frames(request.observation.frame_rate_hz))
    if sink is not None and hasattr(sink, "describe"):
        _describe(sink, request, cal, gains, 1.0 / loop.mas_per_nm_tt)
    return n_close, tasks, gains


def _describe(sink, request: RunRequest, cal: Calibration, gains: LoopGains, nm_per_mas: float) -> None:
    """The loop's static description to the sink, before the first frame: rate, delay, modes,
    the configuration, the reconstructor and the modal basis."""
    obs = request.observation
    described = {"rate_hz": obs.frame_rate_hz, "delay_frames": obs.delay_frames, "n_modes": cal.basis.n_modes} | LBT_SYSTEM
    num, den = coefficient_rows(unit_loops(obs, request.structure, gains.forgetting, cal.basis.n_modes)[0])
    static = {"reconstructor": cal.reconstructor, "modes_to_commands": cal.basis.M, "controller_num": num, "controller_den": den}
    configuration = run_configuration(request, gains) | {"tip_tilt_nm_per_mas": nm_per_mas}
    sink.describe(described, configuration, static)


def loop_calibration(request: RunRequest, cal: Calibration) -> Calibration:
    """The calibration the loop's RTC holds: ``cal`` (noiseless), or with the request's
    calibration noise the one measured in those conditions (seeded, so the same each time)."""
    if request.calibration_noise is None:
        return cal
    return measured_calibration(cal, request.calibration_noise, L0_m=request.L0_m)


def closed_loop_for(
    request: RunRequest, cal: Calibration, gains: LoopGains, structure, sink: Sink | None = None, duration_s: float | None = None
) -> ClosedLoop:
    """The request's closed loop at t = 0 (its turbulence, vibrations, noise, structure,
    mis-registration, NCPA and calibration noise, seeded by its seed), with ``gains``;
    ``structure`` sampled at its rate; turbulence that does not repeat within ``duration_s``
    (default: the request's).  With calibration noise the loop's interaction matrix
    and reconstructor are the measured ones (``cal``, noiseless, stays what the optical-gain
    tables and the checks use)."""
    pupil = cal.setup.pyramid.pupil
    cal = loop_calibration(request, cal)
    return ClosedLoop(
        request.observation,
        cal,
        request.atmosphere(),
        gains,
        vibrations=request.vibrations,
        noise=request.noise,
        seed=request.seed,
        structure=structure,
        sink=sink,
        registration=request.misregistration,
        ncpa=None if request.ncpa is None else non_common_path(request.ncpa, pupil, cal.basis.shapes(pupil), cal.interaction_matrix),
        duration_s=request.duration_s if duration_s is None else duration_s,
    )


def _offsets_note(loop: ClosedLoop) -> tuple[str, ...]:
    """A note when the NCPA offsets waited for OGTL to calibrate k and the run ended first."""
    if loop.rtc_parameters.held_offset is None:
        return ()
    tolerance = f"{OFFSETS_CHI_TOLERANCE:.0%}".replace("%", " %")
    return (f"the NCPA offsets were never applied: OGTL did not calibrate k (chi within {tolerance} of 1) within the run",)


def _repeat_note(loop: ClosedLoop, request: RunRequest) -> tuple[str, ...]:
    """A note when the run outlasts its screens (longer than ``MAX_SCREEN_PIXELS`` allows: its
    turbulence then repeats)."""
    atmosphere = loop.disturbance.atmosphere
    if atmosphere is None or request.duration_s <= (repeat := atmosphere.repeat_time_s):
        return ()
    largest = max(atmosphere.screen_shapes, key=lambda shape: shape[0] * shape[1])
    return (
        f"the turbulence repeats after {repeat:.3g} s (periodic screens of at most {largest[0]} x {largest[1]} px; "
        f"this run lasts {request.duration_s:g} s): later frames see the same screens again",
    )


def run(
    request: RunRequest,
    cache: ArrayCache = ArrayCache(None),
    progress=None,
    aux=None,
    calibration: Calibration | None = None,
    sink: Sink | None = None,
) -> RunResult:
    """Calibrate, close the loop for ``request.frames`` frames, reduce (see the module).

    Parameters
    ----------
    request : RunRequest
        The resolved run (``run_config.RunConfig.request`` builds it from a description).
    cache : ArrayCache
        Where the calibration (basis, interaction matrix) is reused from; none by default.
    progress : callable or None
        Called with the frames done after each frame; None: silent.
    aux : loop.optimize.LiveOptimisers or None
        MGM and/or OGTL beside the loop once it has closed (`loop run --mgm --ogtl`).
    calibration : Calibration or None
        The request's calibration, already computed (a sweep shares it); None: computed or
        read from ``cache``.
    sink : Sink or None
        Where every frame's records go (``telemetry.stream.Hdf5Writer``), described (rate,
        delay, modes, configuration) before the first frame.

    Returns
    -------
    RunResult
        The request, the gains the run ended with, the calibration, the telemetry kept in
        memory, the metrics (None for a loop that never closed) and the long-exposure PSF.
    """
    obs = request.observation
    structure = request.sampled_structure()
    gains = request.design_gains()
    if not request.allow_unstable:
        check_stability(obs, gains, structure)
    t0 = time.perf_counter()
    cal = calibration or calibration_for(request, cache)
    t_cal = time.perf_counter() - t0
    loop = closed_loop_for(request, cal, gains, structure, sink)
    loop.telemetry.moments_from(request.skip)
    n_close, tasks, gains = _prepare(loop, request, gains, cal, cache, aux, sink)
    psf = loop.psf_accumulator(band_wavelength(request.band))
    diverged_at = diverged_rms = None
    t1 = time.perf_counter()
    try:
        _close_and_run(loop, request, psf, n_close, tasks, progress)
    except LoopDiverged as e:
        diverged_at, diverged_rms = e.frame, e.residual_nm
    seconds = time.perf_counter() - t1
    metrics, image, coupling = None, None, None
    spectra: dict = {}
    if diverged_at is None:
        coupling = registration_stability(request, cal, loop, gains.forgetting, structure, cache)
        metrics, spectra = _metrics(request, loop.telemetry, psf, loop.mas_per_nm_tt)
        image = psf.psf
    return RunResult(
        request,
        gains,
        cal,
        loop.telemetry,
        metrics,
        image,
        diverged_at,
        diverged_rms,
        seconds,
        t_cal,
        loop.mas_per_nm_tt,
        spectra,
        loop.rtc_parameters.gains,
        loop.rtc_parameters.sensitivity,
        loop.notes + _repeat_note(loop, request) + _offsets_note(loop),
        coupling,
    )
