"""OGTL's lock-in estimate of chi and its sensitivity update (soulctl.control.ogtl)."""

import math

import numpy as np
import pytest

from soulctl.control.ogtl import OgtlSettings, demodulate, held_sensitivity, optical_gain_estimate, updated_sensitivity
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


def test_sensitivity_update_drives_chi_to_one_and_ignores_bad_estimates():
    gamma, k = 0.25, 1.0
    for _ in range(30):
        k = updated_sensitivity(k, gamma * k, 0.5)
    assert gamma * k == pytest.approx(1.0, rel=1e-3)
    assert updated_sensitivity(2.0, math.nan, 0.5) == 2.0
    assert updated_sensitivity(2.0, -0.3, 0.5) == 2.0
    assert updated_sensitivity(1.0, 1e-9, 1.0) == 20.0  # clipped


def test_probe_frequency_defaults_to_a_quarter_of_the_rate_and_must_be_below_nyquist():
    assert OgtlSettings().probe_frequency(1700.0) == 425.0
    with pytest.raises(InputError, match="below Nyquist"):
        OgtlSettings(frequency_hz=600.0).probe_frequency(1000.0)
    for bad in ({"mode": 0}, {"amplitude_nm": 0.0}, {"gain": 1.5}, {"frequency_hz": -1.0}):
        with pytest.raises(InputError):
            OgtlSettings(**bad)


def test_k_is_held_while_the_commands_grow_and_only_raised_then():
    assert held_sensitivity(2.0, 2.5, 140.0, 100.0, 1.3) == (2.0, True)  # growing 40 %: not raised
    assert held_sensitivity(2.0, 2.5, 120.0, 100.0, 1.3) == (2.5, False)  # 20 %: raised
    assert held_sensitivity(2.0, 1.5, 300.0, 100.0, 1.3) == (1.5, False)  # lowering is always allowed
    assert held_sensitivity(2.0, 2.5, 300.0, None, 1.3) == (2.5, False)  # first update
    assert held_sensitivity(2.0, 2.5, 300.0, 100.0, float("inf")) == (2.5, False)  # rule off
