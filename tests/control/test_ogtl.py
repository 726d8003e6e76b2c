"""OGTL's lock-in estimate of chi, its standard error, and the sensitivity update's rules:
reliability, bounds, rate and growth (soulctl.control.ogtl)."""

import math

import numpy as np
import pytest

from soulctl.control import ogtl
from soulctl.control.ogtl import Estimate, OgtlSettings, default_amplitude, demodulate, estimate, next_sensitivity, optical_gain_estimate
from soulctl.errors import InputError


def test_demodulation_recovers_a_sinusoid_amplitude_and_phase():
    rate, f = 1000.0, 250.0
    k = 17 + np.arange(4000)
    x = 3.0 * np.sin(2 * np.pi * f * k / rate + 0.4) + 5.0
    a = demodulate(x, f, rate, first_frame=17)
    assert abs(a) == pytest.approx(3.0, rel=1e-9)
    assert np.angle(a) == pytest.approx(0.4 - np.pi / 2, abs=1e-9)


@pytest.mark.parametrize("chi", [0.3, 1.0, 1.7])
def test_chi_is_recovered_under_turbulence_and_noise(chi):
    """m = chi (x - y) + n with x, n uncorrelated with the probe on the mirror y."""
    rng = np.random.default_rng(1)
    rate, f, n = 1700.0, 425.0, 1700
    k = np.arange(n)
    x = np.cumsum(rng.normal(0, 2.0, n))  # a random walk: red, like turbulence
    y = 20.0 * np.sin(2 * np.pi * f * k / rate) + 0.8 * x  # the probe plus the loop tracking x
    m = chi * (x - y) + rng.normal(0, 10.0, n)
    assert optical_gain_estimate(m, y, f, rate) == pytest.approx(chi, rel=0.05)


def test_sensitivity_update_drives_chi_to_one_within_its_bounds_and_rate():
    gamma, k, settings = 0.25, 1.0, OgtlSettings()
    ks = []
    for _ in range(30):
        k, status = next_sensitivity(k, Estimate(gamma * k, 0.01, 100.0), settings, k_max=10.0)
        ks.append(k)
    assert gamma * k == pytest.approx(1.0, rel=1e-3)
    steps = np.diff(np.log([1.0] + ks))
    assert np.max(np.abs(steps)) <= np.log(ogtl.MAX_STEP) + 1e-12  # at most a factor MAX_STEP per update
    assert steps[0] == pytest.approx(np.log(ogtl.MAX_STEP))  # the integrator asked for 2: limited
    # bounds: [1, k_max]
    assert next_sensitivity(4.9, Estimate(0.01, 0.001, 10.0), settings, k_max=5.0) == (5.0, ogtl.AT_BOUND)
    assert next_sensitivity(1.1, Estimate(3.0, 0.1, 30.0), settings, k_max=5.0) == (1.0, ogtl.AT_BOUND)
    assert next_sensitivity(30.0, Estimate(1.0, 0.1, 10.0), settings, k_max=5.0)[0] == 5.0  # a k outside comes back in


def test_k_is_held_when_the_estimate_is_unreliable_or_absent():
    settings = OgtlSettings()
    assert next_sensitivity(2.0, Estimate(0.5, 0.2, 2.5), settings, k_max=10.0) == (2.0, ogtl.LOW_SNR)
    assert next_sensitivity(2.0, Estimate(math.nan, math.nan, math.nan), settings, k_max=10.0) == (2.0, ogtl.NO_ESTIMATE)
    assert next_sensitivity(2.0, Estimate(-0.3, 0.01, 30.0), settings, k_max=10.0) == (2.0, ogtl.NO_ESTIMATE)
    k, status = next_sensitivity(2.0, Estimate(0.9, 0.9 / 5.0, 5.0), settings, k_max=10.0)  # at the threshold: moves
    assert k == pytest.approx(2.0 * 0.9**-0.5) and status == ogtl.UPDATED


def test_k_is_not_raised_while_the_commands_grow_but_may_be_lowered():
    settings = OgtlSettings()
    assert next_sensitivity(2.0, Estimate(0.8, 0.01, 80.0), settings, 10.0, growing=True) == (2.0, ogtl.GROWING)
    k, status = next_sensitivity(2.0, Estimate(1.2, 0.01, 120.0), settings, 10.0, growing=True)
    assert k < 2.0 and status == ogtl.UPDATED
    assert ogtl.commands_growing(140.0, 100.0, 1.3) and not ogtl.commands_growing(120.0, 100.0, 1.3)
    assert not ogtl.commands_growing(300.0, None, 1.3) and not ogtl.commands_growing(300.0, 100.0, math.inf)


@pytest.mark.parametrize("noise", [2.0, 10.0])
def test_the_standard_error_is_the_lock_ins_scatter(noise):
    """sigma_chi from the off-frequency reference matches the scatter of chi_hat over many
    independent windows, and the theory for white noise, sqrt(2 noise^2 / N) / |Y|."""
    rng = np.random.default_rng(3)
    rate, f, n, a, chi = 1000.0, 250.0, 1000, 20.0, 0.4
    k = np.arange(n)
    y = a * np.sin(2 * np.pi * f * k / rate)
    estimates = [estimate(chi * (-y) + rng.normal(0, noise, n), y, f, rate) for _ in range(300)]
    scatter = np.std([e.chi for e in estimates])
    sigma = np.sqrt(np.mean([e.sigma**2 for e in estimates]))
    theory = np.sqrt(2 * noise**2 / n) / a
    assert scatter == pytest.approx(theory, rel=0.15)
    assert sigma == pytest.approx(theory, rel=0.1)
    assert np.mean([e.chi for e in estimates]) == pytest.approx(chi, abs=3 * theory / np.sqrt(300))


def test_a_strong_probe_is_not_its_own_noise():
    """The probe removed before the reference bins: a noiseless probe gives a tiny sigma."""
    rate, f, n = 1000.0, 237.3, 1000  # not a whole number of cycles in the window
    k = np.arange(n)
    y = 20.0 * np.sin(2 * np.pi * f * k / rate)
    e = estimate(-0.5 * y, y, f, rate)
    assert e.chi == pytest.approx(0.5, rel=1e-9) and e.snr > 1e6


def test_default_amplitude_follows_the_noise_within_its_limits():
    assert default_amplitude(0.6, 0.57, 1700) == ogtl.PROBE_AMPLITUDE_NM  # bright: 20 nm is plenty
    a = default_amplitude(12.0, 0.3, 250)
    assert ogtl.PROBE_AMPLITUDE_NM < a < ogtl.MAX_DEFAULT_AMPLITUDE_NM
    assert 0.3 * a / (12.0 * np.sqrt(2 / 250)) == pytest.approx(2 * ogtl.MIN_SNR)  # twice the threshold
    assert default_amplitude(100.0, 0.1, 100) == ogtl.MAX_DEFAULT_AMPLITUDE_NM


def test_probe_frequency_defaults_to_a_quarter_of_the_rate_and_must_be_below_nyquist():
    assert OgtlSettings().probe_frequency(1700.0) == 425.0
    with pytest.raises(InputError, match="below Nyquist"):
        OgtlSettings(frequency_hz=600.0).probe_frequency(1000.0)
    for bad in ({"mode": 0}, {"amplitude_nm": 0.0}, {"gain": 1.5}, {"frequency_hz": -1.0}, {"min_snr": -1.0}, {"max_step": 1.0}):
        with pytest.raises(InputError):
            OgtlSettings(**bad)
