"""The closed loop, one explicit step per frame, in the order a real system runs it:

    1. disturbance at t_k: turbulence (frozen flow) + telescope vibrations on Tip/Tilt;
    2. residual = disturbance - mirror, the mirror holding the delayed commands;
    3. PWFS frame of the residual (optics + detector) -> slopes (C++ SlopeComputer);
    4. RTC step (C++): zeta(k) = Lambda zeta(k-1) + Delta Xi s(k), c(k) = Sigma zeta(k), with
       Xi = B R and Sigma = M C from the reconstructor R and modes-to-commands M;
    5. c(k) enters the delay line; it shapes the mirror from frame k + n on (fractional part
       interpolated, see ``delay_line``); the mirror's Tip/Tilt also drives the 127 Hz
       structural resonance (``control.structure``), whose Tip/Tilt adds to the mirror's;
    6. between two frames, the auxiliary loops (``auxloop``: OGTL, MGM, trial-and-error, live
       metrics) whose period has come read the latest telemetry and may write the gains, the
       slope sensitivity k (slopes are multiplied by k before the RTC) and a modal probe added
       to the commands.

A residual RMS above ``divergence_ratio`` x the largest disturbance RMS so far (at least
10 nm) raises LoopDiverged.

Tip/Tilt take the IIR filter of the observation (or an integrator), the other modes leaky
integrators; gains by the paper's three groups: Tip/Tilt, modes 3-120, modes 121-last.
Telemetry per frame: slopes, commands, their modal projections (R s, M^-1 c), the mirror's
modes during the frame, and the simulation's true residual and disturbance modes (nm), handed
to ``telemetry.recorder.TelemetryRecorder``, which keeps only the auxiliary loops' windows and
the metrics' series and streams every frame to its sink (an HDF5 file) when there is one.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from .. import blas
from ..control.gains import LoopGains, mode_filters
from ..control.structure import StructuralResonance
from ..disturbance.vibrations import VibrationSpectrum
from ..observation import Observation
from ..optics.atmosphere import AtmosphereConfig
from ..optics.calibration import Calibration
from ..optics.detector import Detector
from ..optics.ncpa import NonCommonPath
from ..optics.pwfs import Pyramid
from ..optics.registration import Misregistration
from ..optics.sensor import WavefrontSensor, photons_in_beam
from ..telemetry.recorder import Sink, TelemetryRecorder
from .auxloop import AuxLoop, RtcParameters, TelemetryWindow
from .delay_line import DelayLine
from .metrics import PsfAccumulator
from .stages import AuxScheduler, Controller, Disturbance, Mirror


class LoopDiverged(RuntimeError):
    """The residual grew past ``divergence_ratio`` times the largest disturbance: the loop is
    unstable.
    The telemetry up to and including that frame is kept."""

    def __init__(self, frame: int, residual_nm: float):
        super().__init__(f"loop diverged at frame {frame} (residual {residual_nm:.0f} nm RMS)")
        self.frame = frame
        self.residual_nm = residual_nm


# Stages of a frame, timed in ClosedLoop.stage_seconds (plus "metrics": the PSF in run()).
STAGES = (
    "atmosphere",
    "mirror",
    "wfs_optics",
    "detector",
    "slopes",
    "rtc",
    "telemetry",
)


def _photons_per_frame(observation: Observation, pupil) -> float:
    """Photons of the guide star in the beam per frame (``optics.sensor.photons_in_beam``)."""
    area = pupil.n_valid * pupil.pixel_scale_m**2
    return photons_in_beam(observation.photometry, observation.magnitude_r, observation.frame_rate_hz, area)


class ClosedLoop:
    """A simulated SOUL-like loop for ``observation`` with ``calibration`` (which fixes the
    pyramid's binning, modulation and sampling and the controlled modes); its turbulence does
    not repeat within ``duration_s`` (None: the default screens, ``FrozenFlowAtmosphere``)."""

    @blas.on_one_thread  # the stages' matrices (the mirror's projections, the RTC's) are models too
    def __init__(
        self,
        observation: Observation,
        calibration: Calibration,
        atmosphere: AtmosphereConfig | None,
        gains: LoopGains,
        vibrations: VibrationSpectrum | None = None,
        noise: bool = True,
        seed: int = 1,
        detector: Detector = Detector(),
        delay_frames: float | None = None,
        structure: StructuralResonance | None = StructuralResonance(),
        divergence_ratio: float = 3.0,
        aux_loops: Sequence[AuxLoop] = (),
        sensitivity: float = 1.0,
        sink: Sink | None = None,
        registration: Misregistration | None = None,
        ncpa: NonCommonPath | None = None,
        duration_s: float | None = None,
    ):
        self.observation, self.calibration, self.rate_hz = observation, calibration, observation.frame_rate_hz
        self.rng = np.random.default_rng(seed)
        atm_seed, vib_seed, noise_seed = self.rng.integers(0, 2**63, size=3)
        self.noise_rng = np.random.default_rng(noise_seed) if noise else None
        pyramid = Pyramid(calibration.setup.pyramid)
        self.pupil = pupil = pyramid.pupil
        # the stages, in the order of a frame (``step``)
        self.disturbance = Disturbance(atmosphere, vibrations, pupil, self.rate_hz, int(atm_seed), int(vib_seed), duration_s)
        self.mirror = Mirror(calibration, pupil, structure, self.rate_hz, registration)
        self.sensor = WavefrontSensor(pyramid, detector, _photons_per_frame(observation, pupil))
        self.n_modes = calibration.basis.n_modes
        self.controller = Controller(mode_filters(observation, gains, self.n_modes), calibration)
        self.delay = DelayLine(calibration.basis.M.shape[0], observation.delay_frames if delay_frames is None else delay_frames)
        # the recorder of what the frames produce; R s of float32 slopes
        self.telemetry, self._reconstructor32 = TelemetryRecorder(self.rate_hz, sink), calibration.reconstructor.astype(np.float32)
        # the divergence test's ratio and scale, the largest disturbance RMS so far (nm)
        self.divergence_ratio, self._disturbance_peak = divergence_ratio, 0.0
        self.frame, self.stage_seconds = 0, dict.fromkeys(STAGES + ("metrics",), 0.0)
        self.ncpa = ncpa  # the science path's aberration and the RTC's slope offsets
        offset = None if ncpa is None else ncpa.slope_offset
        self.rtc_parameters = RtcParameters(self.n_modes, gains.per_mode(self.n_modes), self.controller.apply_gains, sensitivity, offset)
        self.scheduler = AuxScheduler(self.rtc_parameters, self.telemetry)
        for aux in aux_loops:
            self.add_aux_loop(aux)

    # what the stages hold, as the loop's callers read it
    notes = property(lambda self: self.disturbance.notes)
    mas_per_nm_tt = property(lambda self: self.disturbance.mas_per_nm_tt)
    rtc = property(lambda self: self.controller.rtc)
    rtc_matrices = property(lambda self: self.controller.rtc_matrices)
    filters = property(lambda self: self.controller.filters)

    def add_aux_loop(self, aux: AuxLoop) -> None:
        """Start an auxiliary loop from the next frame on."""
        self.scheduler.add(aux, self.frame, self.rate_hz)

    def set_gains(self, gains: np.ndarray) -> None:
        """New modal gains from the next frame on (recorded in the gain history)."""
        self.rtc_parameters.set_gains(gains)
        self.scheduler.changed(self.frame)

    def remove_aux_loop(self, aux: AuxLoop) -> None:
        self.scheduler.remove(aux)

    def psf_accumulator(self, wavelength_m: float) -> PsfAccumulator:
        """A long-exposure PSF of this loop's science path (its NCPA included)."""
        return PsfAccumulator(self.pupil, wavelength_m, static_opd=None if self.ncpa is None else self.ncpa.opd)

    def project(self, opd: np.ndarray) -> np.ndarray:
        """Modal coefficients (nm) of an OPD on the pupil pixels (``stages.Mirror.project``)."""
        return self.mirror.project(opd)

    def disturbance_opd(self, k: int) -> np.ndarray:
        """OPD (nm) on the pupil pixels at frame k: turbulence + Tip/Tilt vibrations."""
        return self.disturbance.opd(k)

    def step(self) -> np.ndarray:
        """One frame; returns the residual OPD on the pupil pixels (nm).  The time spent in
        each stage is added to ``stage_seconds``."""
        clock = time.perf_counter
        t0 = clock()
        k = self.frame
        disturbance = self.disturbance.opd(k)
        t1 = clock()
        applied = self.delay.applied()
        mirror, y, disturbance_modes = self.mirror.shape_and_modes(applied, disturbance)
        residual = disturbance - mirror
        piston = residual.mean()
        residual -= piston
        opd = np.zeros((self.pupil.n_pixels,) * 2, dtype=np.float32)
        opd[self.pupil.mask] = residual
        t2 = clock()
        intensity = self.sensor.pyramid.intensity(opd)
        t3 = clock()
        if self.noise_rng is None:
            frame = self.sensor.expected_frame_of(intensity)
        else:
            frame = self.sensor.detector.read(intensity, self.sensor.photons_per_frame, self.noise_rng)
        t4 = clock()
        slopes = self.sensor.slopes_of_frame(frame)
        k_slopes = self.rtc_parameters.sensitivity
        if k_slopes != 1.0:
            slopes *= np.float32(k_slopes)
        if (offset := self.rtc_parameters.slope_offset) is not None:
            scale = self.rtc_parameters.offset_scale  # the RTC's input: k s - chi s_off (optics.ncpa)
            slopes -= offset if scale == 1.0 else np.float32(scale) * offset
        t5 = clock()
        commands = self.controller.commands(slopes, self.rtc_parameters.probe, k, self.rate_hz)
        self.delay.push(commands)
        t6 = clock()
        rms = float(np.sqrt(np.mean(residual**2)))
        self.telemetry.append_frame(
            residual_modes=self.mirror.residual_modes(disturbance_modes, applied, y, piston),
            disturbance_modes=disturbance_modes,
            slopes=slopes,
            commands=commands.copy(),
            measured_modes=self._reconstructor32 @ slopes,
            command_modes=self.calibration.basis.M_inv @ commands,
            mirror_modes=self.calibration.basis.M_inv @ applied,
            residual_rms_nm=rms,
            sensitivity=k_slopes,
            flux=float(frame.sum()),
        )
        t7 = clock()
        for stage, dt in zip(STAGES, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t6 - t5, t7 - t6)):
            self.stage_seconds[stage] += dt
        self.frame += 1
        self._disturbance_peak = max(self._disturbance_peak, float(np.std(disturbance)), 10.0)
        if not np.isfinite(rms) or rms > self.divergence_ratio * self._disturbance_peak:
            raise LoopDiverged(k, rms)
        self.scheduler.run_due(self.frame, self.window, self.rtc.reset)
        return residual

    def window(self, frames: int) -> TelemetryWindow:
        """The last ``frames`` frames, but none from before the latest change of gains or k."""
        start = max(self.frame - frames, self.scheduler.since)

        def rows(name: str) -> np.ndarray:
            return self.telemetry.rows(name, start, self.frame)

        return TelemetryWindow(
            first_frame=start,
            rate_hz=self.rate_hz,
            delay_frames=self.delay.delay_frames,
            measured_modes=rows("measured_modes"),
            command_modes=rows("command_modes"),
            mirror_modes=rows("mirror_modes"),
            slopes=rows("slopes"),
            flux=rows("flux"),
            gains=self.rtc_parameters.gains,
            sensitivity=self.rtc_parameters.sensitivity,
        )

    def run(self, n_frames: int, psf=None, skip: int = 0, progress=None) -> TelemetryRecorder:
        """``n_frames`` steps; the residual of the frames after the first ``skip`` goes into
        ``psf`` (a metrics.PsfAccumulator) when given; ``progress(frames_done)`` after each.

        BLAS runs on one thread meanwhile (``soulctl.blas``: the same numbers on every machine):
        the loop's matrix-vector products are small, and OpenBLAS threads spinning after each
        of them slowed scipy.fft's threads (the pyramid's FFTs) by ~25 % (42 against 34
        iterations/s at 40x40, 160-px pupil)."""
        with blas.one_thread():
            for i in range(n_frames):
                residual = self.step()
                if psf is not None and i >= skip:
                    t0 = time.perf_counter()
                    psf.add(residual)
                    self.stage_seconds["metrics"] += time.perf_counter() - t0
                if progress is not None:
                    progress(i + 1)
        return self.telemetry
