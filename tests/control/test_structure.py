"""The 127 Hz structural resonance in the plant: its shape, and what it does to the loops of
the paper (the integrator's usable gain falls; the IIR keeps its margin)."""

import numpy as np
import pytest

from soulctl.control.filters import Filter
from soulctl.control.structure import StructuralResonance
from soulctl.control.transfer import Loop, Plant, analyze, max_stable_gain
from soulctl.errors import InputError
from soulctl.observation import observation_for_magnitude


@pytest.mark.parametrize("rate", [1000.0, 1700.0])
def test_resonance_peaks_at_127_hz_with_kappa_over_two_zeta(rate):
    r = StructuralResonance()
    f = np.linspace(1, rate / 2 - 1, 20000)
    g = np.abs(r.frequency_response(f, rate))
    assert f[np.argmax(g)] == pytest.approx(127.0, abs=0.5)
    assert g.max() == pytest.approx(r.coupling / (2 * r.damping), rel=0.02)
    assert abs(r.frequency_response(0.1, rate)) < 1e-5  # no static coupling


def test_plant_with_structure_agrees_with_its_polynomials():
    """The frequency response and the numerator/denominator describe the same plant."""
    r = StructuralResonance()
    p = Plant.with_structure(3.57, r, 1700.0)
    w = np.linspace(0.01, np.pi, 50)
    zi = np.exp(-1j * w)
    ratio = np.polyval(p.numerator()[::-1], zi) / np.polyval(p.denominator()[::-1], zi)
    np.testing.assert_allclose(ratio, p.frequency_response(w), rtol=1e-10)


def test_structure_limits_the_1700_hz_integrator_but_not_the_iir():
    obs = observation_for_magnitude(9.7)
    plant = Plant.with_structure(obs.delay_frames, StructuralResonance(), 1700.0)
    integrator = Loop(Filter.integrator(0.3), plant, 1700.0)
    iir = Loop(Filter.iir(obs.tt_zeros, obs.tt_poles, 0.69), plant, 1700.0)
    nominal = max_stable_gain(Loop(Filter.integrator(0.3), Plant(obs.delay_frames), 1700.0))
    g_int = max_stable_gain(integrator)
    assert nominal == pytest.approx(0.52, abs=0.01)
    assert 0.3 < g_int < 0.4  # "well above ~0.2" the integrator is in trouble
    f = np.linspace(100, 160, 3000)
    assert np.abs(integrator.sensitivity(f)).max() > 8  # rings near 127 Hz at g = 0.3
    assert np.abs(integrator.with_gain(0.2).sensitivity(f)).max() < 4
    assert np.abs(iir.sensitivity(f)).max() < 2  # the IIR at its optimised gain does not
    assert analyze(iir).gain_margin > 1.3 and iir.is_stable()


def test_bad_resonances_are_input_errors():
    with pytest.raises(InputError):
        StructuralResonance(damping=0.0)
    with pytest.raises(InputError, match="frame rate above 254"):
        StructuralResonance().coefficients(200.0)
