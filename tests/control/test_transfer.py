"""Loop transfer functions and margins against closed forms and the paper's Tip/Tilt results."""

import math

import numpy as np
import pytest

from soulctl import tables
from soulctl.control.delay import DelayModel
from soulctl.control.filters import Filter
from soulctl.control.transfer import Loop, Plant, analyze, frequency_grid, max_stable_gain
from soulctl.errors import InputError

ROOTS = {r.frame_rate_hz: r for r in tables.tt_iir_table()}


def integrator_loop(g, d, rate=1000.0):
    return Loop(Filter.integrator(g), Plant(d), rate)


@pytest.mark.parametrize("d, g_max", [(1, 2.0), (2, 1.0), (3, (math.sqrt(5) - 1) / 2)])
def test_integrator_stability_limit_closed_form(d, g_max):
    """g/(1 - z^-1) z^-d: stable up to 2 (d = 1), 1 (d = 2), 2 sin(pi/10) = 0.618 (d = 3)."""
    assert max_stable_gain(integrator_loop(0.1, d)) == pytest.approx(g_max, rel=1e-7)
    assert integrator_loop(g_max * (1 - 1e-6), d).is_stable()
    assert not integrator_loop(g_max * (1 + 1e-6), d).is_stable()


@pytest.mark.parametrize("g", [0.2, 0.5, 1.0, 1.5])
def test_integrator_one_frame_margins_closed_form(g):
    """L = g/(z - 1): phase crossover at Nyquist, L = -g/2, so GM = 2/g; |L| = 1 where
    2 sin(w/2) = g, with arg L = -(90 deg + w/2), so PM = 90 deg - asin(g/2)."""
    a = analyze(integrator_loop(g, 1))
    assert a.stable
    assert a.gain_margin == pytest.approx(2.0 / g, rel=1e-9)
    assert a.phase_margin_deg == pytest.approx(90.0 - math.degrees(math.asin(g / 2)), abs=1e-6)
    w_c = 2 * math.asin(g / 2)
    assert a.gain_crossover_hz == pytest.approx(w_c / (2 * math.pi) * 1000.0, rel=1e-6)
    # The modulus margin |1 + g/(z - 1)| = |z - 1 + g| / |z - 1| has its minimum at Nyquist for
    # g <= 1: (2 - g)/2.
    if g <= 1:
        assert a.modulus_margin == pytest.approx((2 - g) / 2, rel=1e-6)


def test_modulus_margin_equals_a_dense_search():
    loop = Loop(Filter.iir(ROOTS[1000].zeros, ROOTS[1000].poles, 1.03), Plant(2.51), 1000.0)
    f = np.linspace(1e-3, 500, 400001)
    brute = np.min(np.abs(1 + loop.open_loop(f)))
    assert analyze(loop).modulus_margin == pytest.approx(brute, rel=1e-6)


@pytest.mark.parametrize(
    "zeros, poles",
    [((), (1.0,)), ((0.5,), (1.0, 0.2)), (ROOTS[1700].zeros, ROOTS[1700].poles), (ROOTS[750].zeros, ROOTS[750].poles), ((), (0.95,))],
)
@pytest.mark.parametrize("d", [1.0, 2.3, 3.567])
def test_max_stable_gain_is_where_the_closed_loop_poles_leave_the_unit_circle(zeros, poles, d):
    loop = Loop(Filter.iir(zeros, poles, 1.0), Plant(d), 1700.0)
    g = max_stable_gain(loop)
    assert loop.with_gain(g * 0.999).is_stable()
    assert not loop.with_gain(g * 1.001).is_stable()
    assert np.max(np.abs(loop.with_gain(g).closed_loop_poles())) == pytest.approx(1.0, abs=1e-6)


def test_optical_gain_scales_the_stable_range():
    """P = chi z^-d: chi multiplies the loop gain, so it divides the maximum stable gain."""
    base = max_stable_gain(Loop(Filter.integrator(0.1), Plant(2.5), 1000))
    assert max_stable_gain(Loop(Filter.integrator(0.1), Plant(2.5, 0.5), 1000)) == pytest.approx(2 * base, rel=1e-9)


# The paper's Tab. TT (rejection at 13 Hz) and its margins (Sec. 4.1), with SOUL's delay model.
PAPER_CASES = [
    # control, rate, gain, rejection, phase margin (deg), gain margin
    ("iir", 1700, 0.69, 0.11, 49, 1.82),
    ("int", 1700, 0.20, 0.24, 51, 2.34),
    ("iir", 1000, 1.03, 0.10, 40, 2.14),
    ("int", 1000, 0.36, 0.23, 51, 2.42),
]


def paper_loop(control, rate, gain, system="soul"):
    d = DelayModel.from_table(system).frames(rate)
    h = Filter.iir(ROOTS[rate].zeros, ROOTS[rate].poles, gain) if control == "iir" else Filter.integrator(gain)
    return Loop(h, Plant(d), float(rate))


@pytest.mark.parametrize("control, rate, gain, rejection, pm, gm", PAPER_CASES)
def test_paper_tip_tilt_table(control, rate, gain, rejection, pm, gm):
    a = analyze(paper_loop(control, rate, gain))
    assert a.stable
    assert a.rejection_13hz == pytest.approx(rejection, abs=0.015)
    assert a.phase_margin_deg == pytest.approx(pm, rel=0.15)
    assert a.gain_margin == pytest.approx(gm, rel=0.15)


def test_paper_soul_integrator_at_gain_04_amplifies_127_hz_more_than_4x():
    """Paper, Sec. 2.3: with a gain of 0.4 at the maximum frame rate |T(127 Hz)| > 4 and the
    -3 dB bandwidth of T is well above 127 Hz."""
    a = analyze(paper_loop("int", 1700, 0.4))
    assert a.noise_127hz > 4.0
    assert a.bandwidth_hz > 1.3 * 127


def test_paper_figure_gains_give_the_same_t_at_127_hz():
    """Paper, Fig. IIR1700TF: gains 0.69 (SOUL-IIR), 0.21 (SOUL-INT) and 0.39 (FLAO-INT, 3.1 ms)
    were chosen to give the same |T(127 Hz)|."""
    t = [
        analyze(paper_loop("iir", 1700, 0.69)).noise_127hz,
        analyze(paper_loop("int", 1700, 0.21)).noise_127hz,
        analyze(paper_loop("int", 1000, 0.39, "flao")).noise_127hz,
    ]
    assert max(t) / min(t) < 1.1


def test_unstable_loop_is_reported_with_its_figures():
    a = analyze(integrator_loop(1.25, 2))
    assert not a.stable
    assert a.gain_margin == pytest.approx(0.8)
    assert a.phase_margin_deg < 0
    assert a.max_stable_gain == pytest.approx(1.0)
    assert a.rejection_13hz is not None and a.to_dict()["stable"] is False
    # |L| > 1 everywhere: no gain crossover, so no phase margin, and still no crash.
    b = analyze(integrator_loop(2.5, 1))
    assert not b.stable and b.phase_margin_deg is None and b.gain_margin == pytest.approx(0.8)


def test_s_plus_t_is_one_and_frequencies_reach_nyquist():
    loop = paper_loop("iir", 1700, 0.69)
    f = frequency_grid(1700.0)
    assert f[0] > 0 and f[-1] == 850.0
    np.testing.assert_allclose(loop.sensitivity(f) + loop.complementary(f), 1.0, atol=1e-12)


def test_figures_beyond_nyquist_are_none():
    a = analyze(integrator_loop(0.3, 1.5, rate=200.0))  # Nyquist 100 Hz < 127 Hz
    assert a.noise_127hz is None and a.rejection_13hz is not None


@pytest.mark.parametrize(
    "kwargs",
    [
        {"delay_frames": -1},
        {"delay_frames": math.nan},
        {"delay_frames": 1, "optical_gain": 0},
        {"delay_frames": 1, "optical_gain": math.inf},
    ],
)
def test_bad_plants(kwargs):
    with pytest.raises(InputError):
        Plant(**kwargs)


def test_bad_rate():
    with pytest.raises(InputError, match="> 0 Hz"):
        Loop(Filter.integrator(0.3), Plant(1), 0.0)
