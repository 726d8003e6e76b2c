"""Loop metrics against closed forms: Strehl by image formation vs Marechal, cumulative
spectra and rejection of known signals, pseudo-open loop alignment."""

import numpy as np
import pytest

from soulctl.errors import InputError
from soulctl.loop.delay_line import DelayLine
from soulctl.loop.metrics import PsfAccumulator, band_wavelength
from soulctl.optics.atmosphere import fft_phase_screen
from soulctl.optics.pupil import Pupil
from soulctl.telemetry.figures import pseudo_open_loop, rejection, tip_tilt_jitter


def test_flat_wavefront_has_unit_strehl():
    acc = PsfAccumulator(Pupil(40), 1.65e-6)
    acc.add(np.zeros(Pupil(40).n_valid))
    assert acc.strehl == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("sigma_rad", [0.2, 0.5])
def test_strehl_of_a_small_random_aberration_is_marechal(sigma_rad):
    """Extended Marechal, SR ~ exp(-sigma^2) for a residual without Tip/Tilt, averaged over
    frames (the long exposure of independent residuals)."""
    pupil = Pupil(48)
    lam = 1.65e-6
    acc = PsfAccumulator(pupil, lam)
    rng = np.random.default_rng(0)
    x, y = pupil.coordinates()
    basis = np.stack([np.ones_like(x), x, y], axis=1)
    for _ in range(20):
        phi = fft_phase_screen(pupil.n_pixels, pupil.pixel_scale_m, 0.05, 25.0, rng)[pupil.mask]
        phi -= basis @ np.linalg.lstsq(basis, phi, rcond=None)[0]  # piston, Tip, Tilt removed
        acc.add(phi / np.std(phi) * sigma_rad * lam * 1e9 / (2 * np.pi))
    assert acc.strehl == pytest.approx(np.exp(-(sigma_rad**2)), rel=0.03)


def test_jitter_and_rejection_of_a_sinusoid():
    rate = 1000.0
    t = np.arange(8192) / rate
    x = 10.0 * np.sin(2 * np.pi * 13.0 * t)
    xy = np.column_stack([x, x])
    j = tip_tilt_jitter(xy, rate, 1.0)
    assert j.resolution_hz <= 1.0
    assert j.total == pytest.approx(10 / np.sqrt(2), rel=0.02)  # all of it below 13 Hz
    assert j.above(3.0) == pytest.approx(j.total, rel=1e-3)
    assert j.cumulative_mas[j.f_hz > 20].max() < 0.1
    other = 0.01 * np.sin(2 * np.pi * 80 * t)
    value, why = rejection(np.column_stack([0.3 * x + other] * 2), xy, rate, 13.0)
    assert why is None and value == pytest.approx(0.3, rel=0.01)


def test_jitter_of_white_noise_is_its_rms_and_a_continuum_has_no_rejection():
    rate = 1700.0
    xy = np.random.default_rng(3).normal(0.0, 5.0, (1700, 2))
    j = tip_tilt_jitter(xy, rate, 2.0)
    assert j.total == pytest.approx(5.0 / 2.0, rel=0.05)
    assert j.above(3.0) == pytest.approx(j.total * np.sqrt(1 - 3.0 / 850), rel=0.05)
    value, why = rejection(xy * 0.5, xy, rate, 13.0)
    assert value is None and "no line at 13 Hz" in why


def test_a_short_window_states_its_resolution_and_leaves_out_what_it_cannot_resolve():
    rate = 1700.0
    xy = np.random.default_rng(4).normal(0.0, 1.0, (272, 2))
    j = tip_tilt_jitter(xy, rate, 1.0)
    assert j.resolution_hz == pytest.approx(rate / 272)
    assert j.above(3.0) is None
    assert rejection(xy, xy, rate, 13.0) == (None, "run too short: 6.25 Hz bins (needs 5 Hz or finer)")
    assert tip_tilt_jitter(xy[:3], rate, 1.0) is None


@pytest.mark.parametrize("d", [1.0, 2.51, 3.57])
def test_pseudo_open_loop_undoes_the_delay_line(d):
    """Commands through the delay line, then back out of telemetry: m + mirror exactly."""
    rng = np.random.default_rng(1)
    commands = rng.normal(size=(50, 3))
    line = DelayLine(3, d)
    mirror = []
    for c in commands:
        mirror.append(line.applied())
        line.push(c)
    measured = rng.normal(size=(50, 3))
    np.testing.assert_allclose(pseudo_open_loop(measured, commands, d), measured + np.array(mirror), atol=1e-12)


def test_unknown_band_is_an_input_error():
    assert band_wavelength("H") == 1.65e-6
    with pytest.raises(InputError, match="accepted R, I, J, H, FeII, Ks"):
        band_wavelength("K")
