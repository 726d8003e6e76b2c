"""Turbulent Tip/Tilt: variance and temporal PSD against Noll (1976) and Conan et al. (1995)."""

import math

import numpy as np
import pytest

from soulctl.disturbance.turbulence import MAS_PER_RAD, TurbulenceTipTilt
from soulctl.errors import InputError
from soulctl.optics.atmosphere import r0_from_seeing

D = 8.222


def kolmogorov_tilt_variance_mas2(t: TurbulenceTipTilt) -> float:
    """Noll: Delta_1 - Delta_3 = 1.0299 - 0.134 rad^2 (D/r0)^(5/3) for both tilts; one axis,
    as an angle: 16 * 0.448 / (4 pi^2) (lambda/D)^2 (D/r0)^(5/3) = 0.1816 (lambda/D)^2 (D/r0)^(5/3)."""
    per_axis = (1.0299 - 0.134) / 2
    lam_d = 500e-9 / D * MAS_PER_RAD
    return 16 * per_axis / (4 * math.pi**2) * lam_d**2 * (D / t.r0_m) ** (5 / 3)


def test_r0_from_seeing():
    assert r0_from_seeing(1.0) == pytest.approx(0.101, abs=0.001)


@pytest.mark.parametrize("seeing", [0.6, 1.0, 1.5])
def test_kolmogorov_tilt_variance_is_nolls(seeing):
    t = TurbulenceTipTilt(seeing, 1e10, 8.0, D)
    assert t.variance_mas2() == pytest.approx(kolmogorov_tilt_variance_mas2(t), rel=0.01)


def test_outer_scale_reduces_tilt_variance():
    """Finite L0 removes the large scales that carry most of the tilt: the ratio falls with L0,
    to 0.14 for L0 = 25 m on an 8 m pupil (domain notes), and goes to 1 for L0 >> D."""
    ref = TurbulenceTipTilt(1.0, 1e10, 8.0, D).variance_mas2()
    ratios = [TurbulenceTipTilt(1.0, L0, 8.0, D).variance_mas2() / ref for L0 in (10, 25, 100, 1e6)]
    assert ratios == sorted(ratios)
    assert ratios[1] == pytest.approx(0.14, rel=0.1)
    assert ratios[-1] > 0.95


@pytest.mark.parametrize("axis", ["mean", "along", "across"])
def test_temporal_psd_integrates_to_the_spatial_variance(axis):
    """Two representations: the frozen-flow PSD integrated over frequency is the 2-D spatial
    integral (same variance on both axes for isotropic turbulence)."""
    t = TurbulenceTipTilt(1.0, 25.0, 8.0, D)
    f = np.geomspace(1e-4, 500, 2500)
    assert np.trapezoid(t.psd(f, axis), f) == pytest.approx(t.variance_mas2(), rel=0.03)


def test_temporal_psd_slopes_conan_1995():
    """Tilt PSD: f^(-2/3) at low frequency (L0 infinite), f^(-17/3) above the cut-off ~0.6 V/D."""
    t = TurbulenceTipTilt(1.0, 1e10, 10.0, D)
    fc = 0.6 * 10.0 / D
    low = t.psd([0.005 * fc, 0.05 * fc])
    high = t.psd([8 * fc, 40 * fc])
    assert math.log(low[1] / low[0]) / math.log(10) == pytest.approx(-2 / 3, abs=0.1)
    assert math.log(high[1] / high[0]) / math.log(5) == pytest.approx(-17 / 3, abs=0.3)


def test_psd_scales_with_seeing_and_wind():
    """PSD(f) = (1/V) F(f/V) r0^(-5/3): faster wind moves the power to higher frequencies."""
    a, b = TurbulenceTipTilt(1.0, 25, 8.0, D), TurbulenceTipTilt(2.0, 25, 16.0, D)
    f = np.array([0.3, 1.0, 3.0])
    ratio = (r0_from_seeing(2.0) / r0_from_seeing(1.0)) ** (-5 / 3)
    np.testing.assert_allclose(b.psd(2 * f), a.psd(f) * ratio / 2, rtol=1e-9)


@pytest.mark.parametrize(
    "kwargs, text", [({"seeing_arcsec": 0}, "seeing"), ({"outer_scale_m": -1}, "outer scale"), ({"wind_speed_m_s": 0}, "wind speed")]
)
def test_bad_parameters(kwargs, text):
    with pytest.raises(InputError, match=text):
        TurbulenceTipTilt(**kwargs)
