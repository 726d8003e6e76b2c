"""Loop metrics against closed forms: Strehl by image formation vs Marechal, cumulative
spectra and rejection of known signals, pseudo-open loop alignment."""

import numpy as np
import pytest

from soulctl.errors import InputError
from soulctl.loop.delay_line import DelayLine
from soulctl.loop.metrics import PsfAccumulator, band_wavelength, cumulative_spectrum, pseudo_open_loop, rejection_at
from soulctl.optics.atmosphere import fft_phase_screen
from soulctl.optics.pupil import Pupil


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


def test_cumulative_spectrum_and_rejection_of_a_sinusoid():
    rate = 1000.0
    t = np.arange(8192) / rate
    x = 10.0 * np.sin(2 * np.pi * 13.0 * t)
    f, cum = cumulative_spectrum(x, rate)
    assert cum[f < 10].min() == pytest.approx(10 / np.sqrt(2), rel=0.02)  # all of it below 13 Hz
    assert cum[f > 20].max() < 0.1
    assert rejection_at(0.3 * x + 0.01 * np.sin(2 * np.pi * 80 * t), x, rate, 13.0) == pytest.approx(0.3, rel=0.01)


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
