"""The closed loop's stages, each alone: the disturbance (vibrations drawn in blocks, the tilt
scale), the mirror (shape and projection are inverse on the controlled modes; the structure's
structure rings on a step, with no static response), the controller (one frame of an integrator)
and the auxiliary loops' scheduler (which task runs when, on which window, the gain history)."""

from types import SimpleNamespace

import numpy as np
import pytest

from soulctl.control.filters import Filter
from soulctl.control.structure import StructuralResonance
from soulctl.disturbance.vibrations import VibrationLine, VibrationSpectrum
from soulctl.loop.auxloop import AuxLoop, RtcParameters
from soulctl.loop.stages import AuxScheduler, Controller, Disturbance, Mirror
from soulctl.optics.calibration import CalibrationSetup, calibrate
from soulctl.optics.pwfs import Pyramid, PyramidConfig
from soulctl.optics.registration import Misregistration

RATE_HZ = 1000.0


@pytest.fixture(scope="module")
def calibration(optics_cache):
    return calibrate(CalibrationSetup(PyramidConfig(binning=4, oversampling=1), 54), optics_cache)


@pytest.fixture(scope="module")
def pupil(calibration):
    return Pyramid(calibration.setup.pyramid).pupil


def test_disturbance_vibrations_are_the_same_series_however_read(pupil):
    spectrum = VibrationSpectrum((VibrationLine(13.0, 0.02, 9.0, 6.5),), "test")
    seq = Disturbance(None, spectrum, pupil, RATE_HZ, 1, np.random.default_rng(5))
    jump = Disturbance(None, spectrum, pupil, RATE_HZ, 1, np.random.default_rng(5))
    series = np.array([seq.tip_tilt_mas(k) for k in range(9000)])  # crosses two blocks
    np.testing.assert_array_equal(jump.tip_tilt_mas(8999), series[-1])
    # the line's RMS per axis (a damped oscillator driven to the stated amplitude), within the
    # scatter of 9 s of a 13 Hz line with 2 % damping
    np.testing.assert_allclose(series.std(axis=0), [9.0, 6.5], rtol=0.35)
    # the OPD of 1 mas of tip, projected back on the pupil's tip ramp, is 1 mas
    opd = np.array([1.0, 0.0]) @ seq.tilt_opd_per_mas
    assert np.sqrt(np.mean((opd - opd.mean()) ** 2)) * seq.mas_per_nm_tt == pytest.approx(1.0)


def test_disturbance_without_turbulence_or_vibrations_is_zero(pupil):
    d = Disturbance(None, None, pupil, RATE_HZ, 1, np.random.default_rng(1))
    assert not d.opd(17).any() and d.notes == ()


@pytest.mark.parametrize("registration", [None, Misregistration(shift_x_pitch=0.3, rotation_deg=1.0)])
@pytest.mark.parametrize("structure", [None, StructuralResonance()])
def test_the_modes_from_one_pass_are_the_direct_projections(calibration, pupil, registration, structure):
    """The mirror's shape and the disturbance's modes come from one pass over F, the residual's
    modes from the disturbance's by linearity: both equal the projections of the OPDs
    themselves, with and without a mis-registration (F' c shapes the mirror, S^T still projects)
    and the structure (its Tip/Tilt in the shape)."""
    rng = np.random.default_rng(3)
    mirror = Mirror(calibration, pupil, structure, RATE_HZ, registration)
    applied = calibration.basis.M @ (rng.standard_normal(calibration.basis.n_modes) * 50.0)
    disturbance = rng.standard_normal(pupil.n_valid) * 300.0
    for _ in range(3):  # the structure rings: its y is not zero after the first frame
        shape, y, modes = mirror.shape_and_modes(applied, disturbance)
    np.testing.assert_array_equal(shape, mirror.influence @ applied + (mirror.shapes_tt @ y if structure else 0.0))
    np.testing.assert_allclose(modes, mirror.project(disturbance), rtol=0, atol=1e-12 * np.abs(modes).max())
    residual = disturbance - shape
    piston = residual.mean()
    direct = mirror.project(residual - piston)
    np.testing.assert_allclose(mirror.residual_modes(modes, applied, y, piston), direct, rtol=0, atol=1e-9 * np.abs(direct).max())
    assert np.abs(direct).max() > 1.0  # a residual worth projecting
    np.testing.assert_array_equal(Mirror(calibration, pupil, None, RATE_HZ, registration).shape(applied)[0], mirror.influence @ applied)


def test_mirror_projection_inverts_its_shape_and_the_structure_responds_statically(calibration, pupil):
    basis = calibration.basis
    a = np.zeros(basis.n_modes)
    a[[0, 5, 30]] = [40.0, -25.0, 10.0]  # nm
    mirror = Mirror(calibration, pupil, None, RATE_HZ)
    shape, y = mirror.shape(basis.M @ a)
    assert not y.any()
    np.testing.assert_allclose(mirror.project(shape), a, atol=0.02 * np.abs(a).max())
    # the structure, G(s) = coupling s^2 / (s^2 + 2 zeta w0 s + w0^2): a step of Tip/Tilt rings
    # it, and it rings down to nothing (no static response)
    shaken = Mirror(calibration, pupil, StructuralResonance(), RATE_HZ)
    first = shaken.shape(basis.M @ a)[1]
    for _ in range(400):
        _, y = shaken.shape(basis.M @ a)
    assert abs(first[0]) > 0.05 * a[0] and abs(y[0]) < 1e-3 * a[0]


def test_controller_one_frame_of_an_integrator(calibration):
    n = calibration.basis.n_modes
    filters = [Filter.integrator(0.5)] + [Filter.integrator(0.0)] * (n - 1)
    controller = Controller(filters, calibration)
    slopes = calibration.interaction_matrix[:, 0].astype(np.float32)  # 1 nm of mode 1, measured
    c = controller.commands(slopes, None, 0, RATE_HZ)
    modes = calibration.basis.M_inv @ c
    assert modes[0] == pytest.approx(0.5, rel=1e-3) and np.abs(modes[1:]).max() < 1e-3
    gains = np.full(n, 0.2)
    controller.apply_gains(gains)
    np.testing.assert_allclose(controller.rtc_matrices.mode_gains(), gains)
    np.testing.assert_allclose(controller.rtc.state_gains, controller.rtc_matrices.Delta, rtol=1e-7)


class _Halver(AuxLoop):
    """Halves the gains at its 2nd update and asks for a reset at its 3rd."""

    name = "halver"

    def update(self, window, rtc):
        self.updates = getattr(self, "updates", 0) + 1
        if self.updates == 2:
            rtc.set_gains(rtc.gains / 2)
        if self.updates == 3:
            rtc.request_reset()
        return {"window": window}


def test_scheduler_runs_tasks_on_their_period_and_windows_start_at_the_last_change():
    params = RtcParameters(3, np.full(3, 0.4), lambda g: None)
    telemetry = SimpleNamespace(gain_history=[], aux={}, keep_window=lambda frames: None)
    scheduler = AuxScheduler(params, telemetry)
    task = _Halver(5)
    scheduler.add(task, 0, RATE_HZ)
    resets, asked = [], []

    def window(frames):
        asked.append(frames)
        return max(frame - frames, scheduler.since)  # the first frame the window would hold

    for frame in range(1, 21):
        scheduler.run_due(frame, window, lambda f=frame: resets.append(f))
    assert [r["frame"] for r in telemetry.aux["halver"]] == [5, 10, 15, 20] and asked == [5] * 4
    assert [r["window"] for r in telemetry.aux["halver"]] == [0, 5, 10, 15]
    assert scheduler.since == 15 and resets == [15]  # the reset of the 3rd update counts as a change
    frames, gains = zip(*telemetry.gain_history)
    assert frames == (0, 10) and np.allclose(gains[1], 0.2)
    scheduler.remove(task)
    scheduler.run_due(25, window, lambda: None)
    assert len(telemetry.aux["halver"]) == 4
