"""The stages of the simulated closed loop, one job each; ``simulation.ClosedLoop`` wires them
and runs them in the order of the real system (disturbance -> mirror and structure -> sensor ->
controller -> delay line -> telemetry -> auxiliary loops).

* ``Disturbance``: the OPD the telescope delivers at frame k, frozen-flow turbulence plus the
  Tip/Tilt vibrations (drawn in blocks, so a loop run in pieces is the same loop).
* ``Mirror``: the adaptive secondary's shape for the applied commands, F c, plus the 127 Hz
  structure excited by its own Tip/Tilt (``control.structure``), and the projections of pupil
  OPDs on the modes.
* ``Controller``: the per-mode filters assembled into Lambda, Xi, Sigma, Delta and run by the
  C++ RTC (the paper's zeta(k) = Lambda zeta(k-1) + Delta Xi s(k), c(k) = Sigma zeta(k)), plus
  the OGTL probe added to the commands.
* ``AuxScheduler``: the auxiliary loops beside the RTC (OGTL, MGM, trial-and-error, the live
  metrics, the safety net): which run at a frame, the window each reads, their records, and
  the history of the gains in force.
The sensor (``optics.sensor.WavefrontSensor``) and the delay line (``delay_line.DelayLine``)
are stages of their own modules.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from .. import _core
from ..control.rtc import build_rtc
from ..control.structure import StructuralResonance
from ..disturbance.vibrations import VibrationSource, VibrationSpectrum
from ..optics.atmosphere import AtmosphereConfig, FrozenFlowAtmosphere
from ..optics.calibration import Calibration
from ..optics.pupil import Pupil
from ..optics.registration import Misregistration
from .auxloop import AuxLoop, RtcParameters, TelemetryWindow

VIBRATION_BLOCK = 4096  # vibration samples drawn at a time


class Disturbance:
    """Turbulence + Tip/Tilt vibrations on the pupil pixels (nm) at frame k."""

    def __init__(
        self,
        atmosphere: AtmosphereConfig | None,
        vibrations: VibrationSpectrum | None,
        pupil: Pupil,
        rate_hz: float,
        atmosphere_seed: int,
        vibration_seed: int,
        duration_s: float | None = None,
    ):
        self.pupil, self.rate_hz, self.vibration_rng = pupil, rate_hz, np.random.default_rng(vibration_seed)
        # screens that do not repeat within duration_s (``FrozenFlowAtmosphere``)
        self.atmosphere = None
        if atmosphere is not None:
            self.atmosphere = FrozenFlowAtmosphere(atmosphere, pupil.n_pixels, pupil.pixel_scale_m, atmosphere_seed, duration_s=duration_s)
        self.vibrations, dropped = vibrations.below_nyquist(rate_hz) if vibrations is not None else (None, ())
        # What the loop changed of what it was given, for the run's report.
        self.notes: tuple[str, ...] = tuple(
            f"the {line.frequency_hz:g} Hz vibration line is left out: at or above the {rate_hz / 2:g} Hz Nyquist frequency "
            "of the loop (a real system aliases or filters it)"
            for line in dropped
        )
        # A tilt of 1 mas is a unit-RMS ramp of RMS(x) * 1 mas (in rad) * 1e9 nm.
        tip, tilt = pupil.tilt()
        nm_per_mas = pupil.nm_per_mas_tilt()
        self.tilt_opd_per_mas = np.stack([tip, tilt]) * nm_per_mas
        self.mas_per_nm_tt = 1.0 / nm_per_mas
        self._source: VibrationSource | None = None
        self._series, self._first = np.zeros((0, 2)), 0

    def tip_tilt_mas(self, k: int) -> np.ndarray:
        """Tip/Tilt vibrations (mas) at frame k, drawn in blocks of VIBRATION_BLOCK frames."""
        if self.vibrations is None:
            return np.zeros(2)
        if self._source is None:
            self._source = VibrationSource(self.vibrations, self.rate_hz, self.vibration_rng)
            self._series, self._first = self._source.next(VIBRATION_BLOCK), 0
        while k >= self._first + len(self._series):
            self._first += len(self._series)
            self._series = self._source.next(VIBRATION_BLOCK)
        return self._series[k - self._first]

    def opd(self, k: int) -> np.ndarray:
        """OPD (nm) on the pupil pixels at frame k."""
        t = k / self.rate_hz
        phi = self.atmosphere.opd_nm(t)[self.pupil.mask] if self.atmosphere else np.zeros(self.pupil.n_valid)
        return phi + self.tip_tilt_mas(k) @ self.tilt_opd_per_mas


def core_influence(F) -> _core.InfluenceFunctions:
    """The C++ core's copy of a CSR matrix of influence functions (``_core.InfluenceFunctions``)."""
    return _core.InfluenceFunctions(F.indptr, F.indices, F.data, F.shape[1])


class Mirror:
    """The adaptive secondary with its structure, and the modal projections of pupil OPDs."""

    def __init__(
        self,
        calibration: Calibration,
        pupil: Pupil,
        structure: StructuralResonance | None,
        rate_hz: float,
        registration: Misregistration | None = None,
    ):
        basis = calibration.basis
        self.basis, self.pupil, self.structure = basis, pupil, structure
        # Influence functions as a sparse matrix F (responses < 1e-4 dropped): the mirror shape
        # is F c and a modal projection S^T r = M^T (F^T r).  The C++ core computes F c and the
        # disturbance's F^T d in one pass over F (``shape_and_modes``): both are memory-bound in
        # the loop, and F is read once instead of twice.
        # With a mis-registration the shape is the moved mirror's, F' c, while the modes that
        # measure the disturbance and residual stay the calibration's (S = F M).
        nominal = basis.geometry.sparse_influence_functions(pupil)  # (n_valid, n_actuators)
        self.moved = registration is not None and not registration.is_identity
        self.influence = basis.geometry.sparse_influence_functions(pupil, registration=registration) if self.moved else nominal
        self._nominal = core_influence(nominal)
        self._influence = core_influence(self.influence) if self.moved else self._nominal
        self._M_t = np.ascontiguousarray(basis.M.T)
        self.shapes_tt = self.influence @ basis.M[:, :2]  # Tip/Tilt shapes (n_valid, 2)
        # The residual's modes follow from the disturbance's: r = d - mirror - piston, and the
        # projection is linear, so P r = P d - (P F) c - (P shapes_tt) y - piston P 1, with
        # small dense matrices instead of a second projection of all pupil pixels per frame.
        n_valid = pupil.n_valid
        nominal_t = nominal.T.tocsr()
        self._project_mirror = self._M_t @ (nominal_t @ self.influence).toarray() / n_valid
        self._project_tt = self._M_t @ (nominal_t @ self.shapes_tt) / n_valid
        self._project_piston = self.project(np.ones(n_valid))
        if structure is not None:
            self._structure_ba = structure.coefficients(rate_hz)
            self._structure_state = np.zeros((2, 2))  # lfilter state per axis (order 2)
        from scipy.signal import lfilter  # here, not at the top: the CLI starts without scipy.signal

        self._lfilter = lfilter

    def _structure_tt(self, applied: np.ndarray) -> np.ndarray:
        """The structure's Tip/Tilt (nm) this frame, excited by the mirror's; its state advances."""
        y = np.zeros(2)
        if self.structure is not None:
            b, a = self._structure_ba
            u = self.basis.M_inv[:2] @ applied  # the mirror's Tip/Tilt (nm)
            for axis in range(2):
                out, self._structure_state[axis] = self._lfilter(b, a, u[axis : axis + 1], zi=self._structure_state[axis])
                y[axis] = out[0]
        return y

    def _with_structure(self, mirror: np.ndarray, y: np.ndarray) -> np.ndarray:
        return mirror + self.shapes_tt @ y if self.structure is not None else mirror

    def shape(self, applied: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(the mirror's OPD on the pupil pixels, the structure's Tip/Tilt in nm) for the
        applied commands; the structure's state advances one frame."""
        y = self._structure_tt(applied)
        return self._with_structure(self._influence.shape(applied), y), y

    def shape_and_modes(self, applied: np.ndarray, disturbance: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``shape`` and the disturbance's modes S^T d / n_valid, F c and F^T d from one pass
        over F (two with a mis-registration: F' c shapes the mirror, F^T d projects)."""
        y = self._structure_tt(applied)
        if self.moved:
            mirror, seen = self._influence.shape(applied), self._nominal.adjoint(disturbance)
        else:
            mirror, seen = self._influence.shape_and_adjoint(applied, disturbance)
        return self._with_structure(mirror, y), y, self._modes(seen)

    def project(self, opd: np.ndarray) -> np.ndarray:
        """Modal coefficients (nm) of an OPD on the pupil pixels: S^T opd / n_valid (the modes
        are orthonormal on the pupil)."""
        return self._modes(self._nominal.adjoint(np.asarray(opd, dtype=np.float64)))

    def _modes(self, seen: np.ndarray) -> np.ndarray:
        """S^T x / n_valid from what the actuators see of x, F^T x: M^T (F^T x) / n_valid."""
        return self._M_t @ seen / self.pupil.n_valid

    def residual_modes(self, disturbance_modes: np.ndarray, applied: np.ndarray, y: np.ndarray, piston: float) -> np.ndarray:
        """The residual's modes from the disturbance's (see ``__init__``)."""
        return disturbance_modes - self._project_mirror @ applied - self._project_tt @ y - piston * self._project_piston


class Controller:
    """The RTC: one filter per mode (``control.gains.mode_filters``) in the C++ core, the gains as
    Delta's diagonal (``rtc_matrices.Delta`` always the one in force), the OGTL probe added to
    the commands."""

    def __init__(self, filters: list, calibration: Calibration):
        self.filters = filters
        self.basis = calibration.basis
        self.rtc_matrices = build_rtc(filters, calibration.reconstructor, calibration.basis.M)
        self.rtc = self.rtc_matrices.controller(n_threads=1)
        self._probe_shape: tuple[int, np.ndarray] | None = None

    def apply_gains(self, gains: np.ndarray) -> None:
        """One gain per mode to the C++ RTC (Delta's diagonal, one value per state)."""
        delta = self.rtc_matrices.delta_from_gains(gains)
        self.rtc.set_state_gains(delta.astype(np.float32))
        self.rtc_matrices = dataclasses.replace(self.rtc_matrices, Delta=delta)

    def commands(self, slopes: np.ndarray, probe, k: int, rate_hz: float) -> np.ndarray:
        """c(k) for the slopes s(k), plus the probe's mode at frame k when there is one."""
        commands = self.rtc.step(slopes)
        if probe is not None:
            commands += np.float32(probe.value(k, rate_hz)) * self._mode_commands(probe.mode)
        return commands

    def _mode_commands(self, mode: int) -> np.ndarray:
        """Actuator commands of one mode (float32), kept for the probe's next frames."""
        if self._probe_shape is None or self._probe_shape[0] != mode:
            self._probe_shape = (mode, self.basis.M[:, mode].astype(np.float32))
        return self._probe_shape[1]


class AuxScheduler:
    """The auxiliary loops' schedule: a task runs when frame % its period == 0, on the last
    period's telemetry but none of it from before the latest change of gains or k (``since``);
    every task of one update reads the same data, at the gains and k that made it.  Keeps the
    telemetry's gain history (one entry per frame at which the gains changed)."""

    def __init__(self, parameters: RtcParameters, telemetry):
        self.parameters, self.telemetry = parameters, telemetry
        self.loops: list[AuxLoop] = []
        self.since = 0  # first frame at the current gains and k
        telemetry.gain_history.append((0, parameters.gains))

    def add(self, aux: AuxLoop, frame: int, rate_hz: float) -> None:
        """Start ``aux`` from the next frame on."""
        aux.start(self.parameters, rate_hz)
        self.telemetry.keep_window(aux.period_frames)
        self.loops.append(aux)
        self.telemetry.aux.setdefault(aux.name, [])
        self.changed(frame)

    def remove(self, aux: AuxLoop) -> None:
        self.loops.remove(aux)

    def changed(self, frame: int) -> None:
        """The gains or k may have changed at ``frame``: windows start there, gains recorded."""
        self.since = frame
        history = self.telemetry.gain_history
        gains = self.parameters.gains
        if np.array_equal(history[-1][1], gains):
            return
        if history[-1][0] == frame:
            history.pop()
        history.append((frame, gains))

    def run_due(self, frame: int, window: Callable[[int], TelemetryWindow], reset_rtc: Callable[[], None]) -> None:
        """The tasks due at ``frame``; ``window(frames)`` gives a task its data."""
        due = [aux for aux in self.loops if frame % aux.period_frames == 0]
        if not due:
            return
        params = self.parameters
        before = (params.gains, params.sensitivity)
        windows = [window(aux.period_frames) for aux in due]
        for aux, data in zip(due, windows):
            record = aux.update(data, params)
            if record:
                self.telemetry.aux[aux.name].append({"frame": frame, **record})
        if not np.array_equal(before[0], params.gains) or before[1] != params.sensitivity or params.reset_requested:
            self.changed(frame)
        if params.reset_requested:
            reset_rtc()
            params.reset_requested = False
