"""RTC assembly from per-mode filters (paper, the mixed-control equations): impulse responses
of the assembled RTC against the filters' difference equations, layout and state budget."""

import numpy as np
import pytest
from scipy.signal import lfilter

from soulctl import tables
from soulctl.control.filters import Filter
from soulctl.control.rtc import SOUL_STATE_SIZE, build_rtc, modes_that_fit
from soulctl.errors import InputError


def impulse_response_through_rtc(filters, n_steps=60):
    """Feed a unit impulse on each mode's slope (R = I, M = I) and read that mode's command."""
    n = len(filters)
    mats = build_rtc(filters, np.eye(n), np.eye(n), state_size=sum(f.n_states for f in filters))
    out = {}
    for mode in range(n):
        rtc = mats.controller()
        s = np.zeros(n, np.float32)
        s[mode] = 1.0
        resp = [rtc.step(s)]
        s[mode] = 0.0
        resp += [rtc.step(s) for _ in range(n_steps - 1)]
        resp = np.array(resp)
        others = np.delete(resp, mode, axis=1)
        assert np.all(others == 0), "an impulse on one mode leaked into another"
        out[mode] = resp[:, mode]
    return out


def difference_equation_impulse(zeros, poles, gain, n_steps=60):
    """Impulse response of H(z) = g prod(1 - beta z^-1) / prod(1 - alpha z^-1), straight from the
    roots with numpy/scipy (independent of the state-space realisation)."""
    x = np.zeros(n_steps)
    x[0] = 1.0
    return lfilter(gain * np.poly(zeros), np.poly(poles), x)


def test_paper_tip_tilt_filters_and_leaky_integrators():
    roots = tables.tt_iir_table()
    gains = {1700: 0.69, 1350: 0.8, 1000: 1.03, 750: 0.5}
    filters = [Filter.iir(r.zeros, r.poles, gains[int(r.frame_rate_hz)]) for r in roots]
    filters += [Filter.leaky(0.99, 0.4), Filter.leaky(0.9, 0.25), Filter.integrator(0.3)]
    got = impulse_response_through_rtc(filters)
    for mode, f in enumerate(filters):
        expected = difference_equation_impulse(f.zeros, f.poles, f.gain)
        np.testing.assert_allclose(got[mode], expected, rtol=1e-4, atol=1e-5 * np.max(np.abs(expected)))


def test_leaky_integrator_is_the_papers_scalar_state_space():
    """N_f = 1: A = alpha, B = g, C = 1 (paper, after Eq. tfIIR); RTC: Lambda = F, Xi = R, Sigma = M."""
    rng = np.random.default_rng(0)
    R = rng.normal(size=(3, 5))
    M = rng.normal(size=(4, 3))
    alphas, gains = [0.9, 0.95, 1.0], [0.1, 0.2, 0.3]
    mats = build_rtc([Filter.leaky(a, g) for a, g in zip(alphas, gains)], R, M, state_size=3)
    np.testing.assert_array_equal(mats.Lambda, np.diag(alphas))
    np.testing.assert_array_equal(mats.Xi, R)
    np.testing.assert_array_equal(mats.Sigma, M)
    np.testing.assert_array_equal(mats.Delta, gains)


def test_gain_lives_only_in_delta():
    zeros, poles = [0.3, 0.5], [0.2, 1.0]
    a = build_rtc([Filter.iir(zeros, poles, 0.3)], np.eye(1), np.eye(1), state_size=4)
    b = build_rtc([Filter.iir(zeros, poles, 1.7)], np.eye(1), np.eye(1), state_size=4)
    for name in ("Lambda", "Xi", "Sigma"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    np.testing.assert_array_equal(a.Delta * (1.7 / 0.3), b.Delta)


def test_uncontrolled_modes_have_no_state_and_no_command():
    rng = np.random.default_rng(1)
    R = rng.normal(size=(4, 6))
    M = np.eye(4)
    mats = build_rtc([Filter.integrator(0.5), None, Filter.leaky(0.99, 0.3)], R, M, state_size=5)
    assert [b.mode for b in mats.blocks] == [0, 2]
    np.testing.assert_array_equal(mats.mode_gains(), [0.5, 0.0, 0.3, 0.0])
    rtc = mats.controller()
    c = np.array([rtc.step(rng.normal(size=6).astype(np.float32)) for _ in range(10)])
    assert np.all(c[:, [1, 3]] == 0) and np.all(c[:, [0, 2]] != 0)


def test_delta_from_gains_round_trip():
    mats = build_rtc([Filter.iir([0.3], [1.0], 1.0), Filter.integrator(0.5), None], np.eye(3), np.eye(3), state_size=6)
    delta = mats.delta_from_gains([0.7, 0.2, 0.9])
    np.testing.assert_array_equal(delta, [0.7, 0.7, 0.2, 0, 0, 0])
    np.testing.assert_array_equal(mats.mode_gains(delta), [0.7, 0.2, 0.0])
    with pytest.raises(InputError, match="expected 3 values"):
        mats.delta_from_gains([0.1, 0.2])


def test_state_budget_says_how_many_modes_fit():
    tt = Filter.iir([0.1, 0.2, 0.3, 0.4], [0.1, 0.2, 0.3, 1.0], 0.5)
    filters = [tt, tt] + [Filter.leaky(0.99, 0.3)] * 657  # 16 + 657 = 673 > 672
    assert modes_that_fit(filters, SOUL_STATE_SIZE) == 658
    with pytest.raises(InputError, match="need 673 states but the RTC has 672: .* only the first 658 modes fit"):
        build_rtc(filters, np.zeros((659, 10)), np.zeros((672, 659)))
    # SOUL's bright-star case: 2 IIR + 498 leaky = 514 states fit
    mats = build_rtc([tt, tt] + [Filter.leaky(0.99, 0.3)] * 498, np.zeros((500, 10)), np.zeros((672, 500)))
    assert mats.used_states == 514 and mats.n_states == 672


def test_shape_errors():
    with pytest.raises(InputError, match="M: expected shape"):
        build_rtc([Filter.integrator(1)], np.zeros((2, 4)), np.zeros((3, 3)))
    with pytest.raises(InputError, match="3 filters given but R has only 2 modes"):
        build_rtc([Filter.integrator(1)] * 3, np.zeros((2, 4)), np.zeros((3, 2)))
