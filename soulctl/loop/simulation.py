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
modes during the frame, and the simulation's true residual and disturbance modes (nm).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter
from threadpoolctl import threadpool_limits

from ..control.filters import Filter
from ..control.rtc import build_rtc
from ..control.structure import StructuralResonance
from ..control.trial import MID_GROUP_END  # the paper's gain groups: 1-2, 3-120, 121-last
from ..disturbance.turbulence import MAS_PER_RAD
from ..disturbance.vibrations import VibrationSource, VibrationSpectrum
from ..errors import InputError
from ..observation import Observation
from ..optics.atmosphere import AtmosphereConfig, FrozenFlowAtmosphere
from ..optics.calibration import Calibration
from ..optics.detector import Detector
from ..optics.pwfs import Pyramid
from ..optics.sensor import WavefrontSensor, photons_in_beam
from .auxloop import AuxLoop, RtcParameters, TelemetryWindow
from .delay_line import DelayLine


class LoopDiverged(RuntimeError):
    """The residual grew past ``divergence_ratio`` times the largest disturbance: the loop is
    unstable.
    The telemetry up to and including that frame is kept."""

    def __init__(self, frame: int, residual_nm: float):
        super().__init__(f"loop diverged at frame {frame} (residual {residual_nm:.0f} nm RMS)")
        self.frame = frame
        self.residual_nm = residual_nm


DEFAULT_FORGETTING = 0.99  # of the leaky integrators of modes 3..last (proposal)
VIBRATION_BLOCK = 4096  # frames of vibrations drawn at a time
# Stages of a frame, timed in ClosedLoop.stage_seconds (plus "metrics": the PSF in run()).
STAGES = (
    "atmosphere",
    "mirror",
    "wfs_optics",
    "detector",
    "slopes",
    "rtc",
    "telemetry",
)  # the paper's gain groups: modes 1-2, 3-120, 121-last


@dataclass(frozen=True)
class LoopGains:
    tip_tilt: float
    mid: float
    high: float
    forgetting: float = DEFAULT_FORGETTING
    modes: tuple[float, ...] | None = None  # one gain per mode (a gain file): overrides the groups

    def __post_init__(self):
        for name in ("tip_tilt", "mid", "high"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0 <= v <= 10):
                raise InputError(f"gain {name} must be a number in 0..10, got {v}")
        if not (0 <= self.forgetting <= 1):
            raise InputError(f"forgetting factor must be in 0..1, got {self.forgetting}")
        if self.modes is not None and not all(math.isfinite(v) and 0 <= v <= 10 for v in self.modes):
            raise InputError("per-mode gains must be numbers in 0..10")

    @classmethod
    def from_modes(cls, gains, forgetting: float = DEFAULT_FORGETTING) -> LoopGains:
        g = tuple(float(x) for x in gains)
        if len(g) < 2:
            raise InputError(f"a per-mode gain list needs at least the 2 Tip/Tilt gains, got {len(g)}")
        mid = g[2:MID_GROUP_END] or (0.0,)
        high = g[MID_GROUP_END:] or (0.0,)
        return cls(g[0], float(np.mean(mid)), float(np.mean(high)), forgetting, g)

    def per_mode(self, n_modes: int) -> np.ndarray:
        if self.modes is not None:
            if len(self.modes) != n_modes:
                raise InputError(f"the gain file has {len(self.modes)} gains but {n_modes} modes are controlled")
            return np.array(self.modes)
        g = np.full(n_modes, self.high)
        g[2:MID_GROUP_END] = self.mid
        g[:2] = self.tip_tilt
        return g


def mode_filters(observation: Observation, gains: LoopGains, n_modes: int) -> list[Filter]:
    """Tip/Tilt: the observation's IIR (unit-gain zeros/poles, times the Tip/Tilt gain) or an
    integrator; the other modes leaky integrators."""
    g = gains.per_mode(n_modes)

    def tip_tilt(gain: float) -> Filter:
        if observation.tt_control == "iir":
            return Filter.iir(observation.tt_zeros, observation.tt_poles, gain)
        return Filter.integrator(gain)

    return [tip_tilt(float(g[0])), tip_tilt(float(g[1]))] + [Filter.leaky(gains.forgetting, float(gi)) for gi in g[2:]]


# Memory of the telemetry kept per frame beyond its arrays' bytes (the arrays' Python objects and
# the lists' slots; measured 1.2 kB at 20x20, 250 modes), and the peak over the lists' own
# size: at the end of a run the lists, their arrays and the file's conversions coexist.
TELEMETRY_OBJECT_BYTES = 1500
TELEMETRY_PEAK_FACTOR = 3


def telemetry_bytes(frames: int, n_slopes: int, n_actuators: int, n_modes: int) -> int:
    """Peak memory of the telemetry of ``frames`` frames, all kept in memory (``Telemetry``):
    float32 slopes, commands and measured modes, float64 command, mirror, residual and
    disturbance modes."""
    per_frame = 4 * (n_slopes + n_actuators + n_modes) + 32 * n_modes + TELEMETRY_OBJECT_BYTES
    return TELEMETRY_PEAK_FACTOR * per_frame * frames


@dataclass
class Telemetry:
    """Per-frame records (rows = frames)."""

    rate_hz: float
    residual_modes: list = field(default_factory=list)  # (n_modes,) nm, projection of the residual OPD
    disturbance_modes: list = field(default_factory=list)  # (n_modes,) nm, of turbulence + vibrations
    measured_modes: list = field(default_factory=list)  # (n_modes,) nm, R s(k)
    command_modes: list = field(default_factory=list)  # (n_modes,) nm, M^-1 c(k)
    mirror_modes: list = field(default_factory=list)  # (n_modes,) nm, the mirror during frame k
    residual_rms_nm: list = field(default_factory=list)
    slopes: list = field(default_factory=list)  # (n_slopes,) float32, scaled by k
    commands: list = field(default_factory=list)  # (n_actuators,) float32, c(k)
    sensitivity: list = field(default_factory=list)  # k during frame k
    flux: list = field(default_factory=list)  # detected electrons in the frame
    # Gains in force from a frame on: [(frame, gains)], the first at frame 0.
    gain_history: list = field(default_factory=list, repr=False)
    # Auxiliary loops' records: name -> [{"frame": f, ...}], f the first frame after the update.
    aux: dict = field(default_factory=dict, repr=False)

    def arrays(self) -> dict[str, np.ndarray]:
        """Per-frame records as arrays (rows = frames)."""
        return {k: np.asarray(v) for k, v in self.__dict__.items() if isinstance(v, list) and k != "gain_history"}

    def aux_arrays(self, name: str) -> dict[str, np.ndarray]:
        """One auxiliary loop's records as arrays (rows = updates)."""
        records = self.aux.get(name, [])
        return {key: np.asarray([r[key] for r in records]) for key in (records[0] if records else {})}

    def gain_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(frames where gains were set, (changes, n_modes) gains)."""
        return np.array([f for f, _ in self.gain_history]), np.array([g for _, g in self.gain_history])


class ClosedLoop:
    """A simulated SOUL-like loop for ``observation`` with ``calibration`` (which fixes the
    pyramid's binning, modulation and sampling and the controlled modes)."""

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
    ):
        self.observation = observation
        self.calibration = calibration
        self.rate_hz = observation.frame_rate_hz
        self.rng = np.random.default_rng(seed)
        atm_seed, vib_seed, noise_seed = self.rng.integers(0, 2**63, size=3)
        self.noise_rng = np.random.default_rng(noise_seed) if noise else None
        self.vibration_rng = np.random.default_rng(vib_seed)
        pyramid = Pyramid(calibration.setup.pyramid)
        pupil = pyramid.pupil
        photons = photons_in_beam(observation.photometry, observation.magnitude_r, self.rate_hz, pupil.n_valid * pupil.pixel_scale_m**2)
        self.sensor = WavefrontSensor(pyramid, detector, photons)
        self.pupil = pupil
        self.atmosphere = FrozenFlowAtmosphere(atmosphere, pupil.n_pixels, pupil.pixel_scale_m, int(atm_seed)) if atmosphere else None
        self.vibrations, dropped = vibrations.below_nyquist(self.rate_hz) if vibrations is not None else (None, ())
        # What the loop changed of what it was given, for the run's report.
        self.notes: tuple[str, ...] = tuple(
            f"the {line.frequency_hz:g} Hz vibration line is left out: at or above the {self.rate_hz / 2:g} Hz Nyquist frequency "
            "of the loop (a real system aliases or filters it)"
            for line in dropped
        )
        basis = calibration.basis
        # Influence functions as a sparse matrix (responses < 1e-4 dropped): the mirror shape is
        # F c and a modal projection S^T r = M^T (F^T r), never the dense S = F M per frame.
        self.influence = basis.geometry.sparse_influence_functions(pupil)  # (n_valid, n_actuators)
        self._influence_t = self.influence.T.tocsr()
        self._M_t = np.ascontiguousarray(basis.M.T)
        self.shapes_tt = self.influence @ basis.M[:, :2]  # Tip/Tilt shapes (n_valid, 2)
        # The disturbance's modes follow from the residual's: d = r + mirror + piston, and the
        # projection is linear, so P d = P r + (P F) c + (P shapes_tt) y + piston P 1, with
        # small dense matrices instead of a second projection of all pupil pixels per frame.
        n_valid = pupil.n_valid
        self._project_mirror = self._M_t @ (self._influence_t @ self.influence).toarray() / n_valid
        self._project_tt = self._M_t @ (self._influence_t @ self.shapes_tt) / n_valid
        self._project_piston = self.project(np.ones(n_valid))
        self._reconstructor32 = calibration.reconstructor.astype(np.float32)  # R s of float32 slopes
        self.n_modes = basis.n_modes
        self.filters = mode_filters(observation, gains, self.n_modes)
        self.rtc_matrices = build_rtc(self.filters, calibration.reconstructor, basis.M)
        self.rtc = self.rtc_matrices.controller(n_threads=1)
        d = observation.delay_frames if delay_frames is None else delay_frames
        self.delay = DelayLine(basis.M.shape[0], d)
        # A tilt of 1 mas is a unit-RMS ramp of RMS(x) * 1 mas (in rad) * 1e9 nm.
        tip, tilt = pupil.tilt()
        x, _ = pupil.coordinates()
        nm_per_mas = float(np.sqrt(np.mean((x - x.mean()) ** 2))) * 1e9 / MAS_PER_RAD
        self._tilt_opd_per_mas = np.stack([tip, tilt]) * nm_per_mas
        self.mas_per_nm_tt = 1.0 / nm_per_mas
        # The structure's Tip/Tilt, excited by the mirror's own Tip/Tilt (control.structure).
        self.structure = structure
        if structure is not None:
            self._structure_ba = structure.coefficients(self.rate_hz)
            self._structure_state = np.zeros((2, 2))  # lfilter state per axis (order 2)
        self.divergence_ratio = divergence_ratio
        self._disturbance_peak = 0.0  # largest disturbance RMS so far (nm): the divergence scale
        self.telemetry = Telemetry(self.rate_hz)
        self.stage_seconds = dict.fromkeys(STAGES + ("metrics",), 0.0)
        self.frame = 0
        self._vibration_source: VibrationSource | None = None
        self.rtc_parameters = RtcParameters(self.n_modes, gains.per_mode(self.n_modes), self._apply_gains, sensitivity)
        self.telemetry.gain_history.append((0, self.rtc_parameters.gains))
        self.aux_loops = list(aux_loops)
        self._parameters_since = 0  # first frame at the current gains and k
        self._probe_shape: tuple[int, np.ndarray] | None = None
        for aux in self.aux_loops:
            aux.start(self.rtc_parameters, self.rate_hz)
            self.telemetry.aux[aux.name] = []

    def add_aux_loop(self, aux: AuxLoop) -> None:
        """Start an auxiliary loop from the next frame on."""
        aux.start(self.rtc_parameters, self.rate_hz)
        self.aux_loops.append(aux)
        self.telemetry.aux.setdefault(aux.name, [])
        self._record_gains()
        self._parameters_since = self.frame

    def set_gains(self, gains: np.ndarray) -> None:
        """New modal gains from the next frame on (recorded in the gain history)."""
        self.rtc_parameters.set_gains(gains)
        self._record_gains()
        self._parameters_since = self.frame

    def _record_gains(self) -> None:
        """Add the current gains to the history if they changed (one entry per frame)."""
        history = self.telemetry.gain_history
        gains = self.rtc_parameters.gains
        if np.array_equal(history[-1][1], gains):
            return
        if history[-1][0] == self.frame:
            history.pop()
        history.append((self.frame, gains))

    def remove_aux_loop(self, aux: AuxLoop) -> None:
        self.aux_loops.remove(aux)

    def _apply_gains(self, gains: np.ndarray) -> None:
        """The gains to the C++ RTC (Delta's diagonal, one value per state), and to the loop's
        ``rtc_matrices``, whose Delta is then never stale."""
        delta = self.rtc_matrices.delta_from_gains(gains)
        self.rtc.set_gains(delta.astype(np.float32))
        self.rtc_matrices = dataclasses.replace(self.rtc_matrices, Delta=delta)

    def project(self, opd: np.ndarray) -> np.ndarray:
        """Modal coefficients (nm) of an OPD on the pupil pixels: S^T opd / n_valid (the modes
        are orthonormal on the pupil)."""
        return self._M_t @ (self._influence_t @ opd) / self.pupil.n_valid

    def _vibration_tt(self, k: int) -> np.ndarray:
        """Tip/Tilt vibrations (mas) at frame k, drawn in blocks of VIBRATION_BLOCK frames (the
        same series however the frames are split between ``run`` calls)."""
        if self.vibrations is None:
            return np.zeros(2)
        if self._vibration_source is None:
            self._vibration_source = VibrationSource(self.vibrations, self.rate_hz, self.vibration_rng)
            self._vibration_series, self._vibration_first = self._vibration_source.next(VIBRATION_BLOCK), 0
        while k >= self._vibration_first + len(self._vibration_series):
            self._vibration_first += len(self._vibration_series)
            self._vibration_series = self._vibration_source.next(VIBRATION_BLOCK)
        return self._vibration_series[k - self._vibration_first]

    def disturbance_opd(self, k: int) -> np.ndarray:
        """OPD (nm) on the pupil pixels at frame k: turbulence + Tip/Tilt vibrations."""
        t = k / self.rate_hz
        phi = self.atmosphere.opd_nm(t)[self.pupil.mask] if self.atmosphere else np.zeros(self.pupil.n_valid)
        return phi + self._vibration_tt(k) @ self._tilt_opd_per_mas

    def step(self) -> np.ndarray:
        """One frame; returns the residual OPD on the pupil pixels (nm).  The time spent in
        each stage is added to ``stage_seconds``."""
        clock = time.perf_counter
        t0 = clock()
        k = self.frame
        disturbance = self.disturbance_opd(k)
        t1 = clock()
        applied = self.delay.applied()
        mirror = self.influence @ applied
        y = np.zeros(2)  # the structure's Tip/Tilt (nm)
        if self.structure is not None:
            b, a = self._structure_ba
            u = self.calibration.basis.M_inv[:2] @ applied  # the mirror's Tip/Tilt (nm)
            for axis in range(2):
                out, self._structure_state[axis] = lfilter(b, a, u[axis : axis + 1], zi=self._structure_state[axis])
                y[axis] = out[0]
            mirror = mirror + self.shapes_tt @ y
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
        t5 = clock()
        commands = self.rtc.step(slopes)
        probe = self.rtc_parameters.probe
        if probe is not None:
            commands += np.float32(probe.value(k, self.rate_hz)) * self._mode_commands(probe.mode)
        self.delay.push(commands)
        t6 = clock()
        tm = self.telemetry
        residual_modes = self.project(residual)
        tm.residual_modes.append(residual_modes)
        tm.disturbance_modes.append(residual_modes + self._project_mirror @ applied + self._project_tt @ y + piston * self._project_piston)
        tm.slopes.append(slopes)
        tm.commands.append(commands.copy())
        tm.measured_modes.append(self._reconstructor32 @ slopes)
        tm.command_modes.append(self.calibration.basis.M_inv @ commands)
        tm.mirror_modes.append(self.calibration.basis.M_inv @ applied)
        rms = float(np.sqrt(np.mean(residual**2)))
        tm.residual_rms_nm.append(rms)
        tm.sensitivity.append(k_slopes)
        tm.flux.append(float(frame.sum()))
        t7 = clock()
        for stage, dt in zip(STAGES, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t6 - t5, t7 - t6)):
            self.stage_seconds[stage] += dt
        self.frame += 1
        self._disturbance_peak = max(self._disturbance_peak, float(np.std(disturbance)), 10.0)
        if not np.isfinite(rms) or rms > self.divergence_ratio * self._disturbance_peak:
            raise LoopDiverged(k, rms)
        self._run_aux_loops()
        return residual

    def _mode_commands(self, mode: int) -> np.ndarray:
        """Actuator commands of one mode (float32), kept for the probe's next frames."""
        if self._probe_shape is None or self._probe_shape[0] != mode:
            self._probe_shape = (mode, self.calibration.basis.M[:, mode].astype(np.float32))
        return self._probe_shape[1]

    def window(self, frames: int) -> TelemetryWindow:
        """The last ``frames`` frames, but none from before the latest change of gains or k."""
        tm = self.telemetry
        start = max(self.frame - frames, self._parameters_since)
        rows = slice(start, self.frame)
        return TelemetryWindow(
            first_frame=start,
            rate_hz=self.rate_hz,
            delay_frames=self.delay.delay_frames,
            measured_modes=np.asarray(tm.measured_modes[rows]),
            command_modes=np.asarray(tm.command_modes[rows]),
            mirror_modes=np.asarray(tm.mirror_modes[rows]),
            slopes=np.asarray(tm.slopes[rows]),
            flux=np.asarray(tm.flux[rows]),
            gains=self.rtc_parameters.gains,
            sensitivity=self.rtc_parameters.sensitivity,
        )

    def _run_aux_loops(self) -> None:
        due = [aux for aux in self.aux_loops if self.frame % aux.period_frames == 0]
        if not due:
            return
        params = self.rtc_parameters
        before = (params.gains, params.sensitivity)
        # Every task of this update reads the same data, at the gains and k that made it.
        windows = [self.window(aux.period_frames) for aux in due]
        for aux, window in zip(due, windows):
            record = aux.update(window, params)
            if record:
                self.telemetry.aux[aux.name].append({"frame": self.frame, **record})
        if not np.array_equal(before[0], params.gains) or before[1] != params.sensitivity or params.reset_requested:
            self._parameters_since = self.frame
            self._record_gains()
        if params.reset_requested:
            self.rtc.reset()
            params.reset_requested = False

    def run(self, n_frames: int, psf=None, skip: int = 0, progress=None) -> Telemetry:
        """``n_frames`` steps; the residual of the frames after the first ``skip`` goes into
        ``psf`` (a metrics.PsfAccumulator) when given; ``progress(frames_done)`` after each.

        BLAS runs on one thread meanwhile: the loop's matrix-vector products are small, and
        OpenBLAS threads spinning after each of them slowed scipy.fft's threads (the pyramid's
        FFTs) by ~25 % (42 against 34 iterations/s at 40x40, 160-px pupil)."""
        with threadpool_limits(limits=1, user_api="blas"):
            for i in range(n_frames):
                residual = self.step()
                if psf is not None and i >= skip:
                    t0 = time.perf_counter()
                    psf.add(residual)
                    self.stage_seconds["metrics"] += time.perf_counter() - t0
                if progress is not None:
                    progress(i + 1)
        return self.telemetry
