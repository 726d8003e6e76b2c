"""Filters: the state-space realisation against the zeros/poles/gain form (paper, Eq. tfIIR)."""

import numpy as np
import pytest

from soulctl import tables
from soulctl.control.filters import Filter
from soulctl.errors import InputError

W = np.linspace(1e-3, np.pi, 400)  # normalised angular frequency, up to Nyquist


def zpk_response(f: Filter, w=W):
    zi = np.exp(-1j * w)
    num = np.prod([1 - b * zi for b in f.zeros], axis=0) if f.zeros else 1.0
    den = np.prod([1 - a * zi for a in f.poles], axis=0)
    return f.gain * num / den


def state_space_response(f: Filter, w=W):
    """H(z) = C (I - A z^-1)^-1 B with B = g B_unit (paper, Eq. tfIIR)."""
    A, B, C = f.unit_state_space()
    n = A.shape[0]
    return np.array([C @ np.linalg.solve(np.eye(n) - A * np.exp(-1j * x), f.gain * B) for x in w])


def paper_filters():
    fs = [Filter.iir(r.zeros, r.poles, 0.7) for r in tables.tt_iir_table()]
    return fs + [
        Filter.integrator(0.4),
        Filter.leaky(0.97, 0.3),
        Filter.iir([0.5], [1.0], 0.2),  # PI-like: one zero, integral action
        Filter.iir([0.2, 0.3], [0.5, 0.6], 1.1),  # no integral action
        Filter.iir([0.5 + 0.3j, 0.5 - 0.3j, 0.1], [0.4 + 0.2j, 0.4 - 0.2j, 1.0], 0.6),  # conjugate pairs
        Filter.iir([0.2, -0.4, 0.6], [0.5], 0.8),  # more zeros than poles
        Filter.iir([0.3, 0.7], [1.0], 0.5),  # a lone integrator with zeros
        Filter.iir([0.3], [1.0, 1.0, 0.5], 0.05),  # repeated poles at 1
        Filter.iir([1.5, 0.2], [0.9, 0.1], 0.4),  # a zero outside the unit circle
    ]


@pytest.mark.parametrize("f", paper_filters(), ids=lambda f: f"{len(f.zeros)}z{len(f.poles)}p")
def test_state_space_equals_zeros_poles_gain(f):
    np.testing.assert_allclose(state_space_response(f), zpk_response(f), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("f", paper_filters(), ids=lambda f: f"{len(f.zeros)}z{len(f.poles)}p")
def test_coefficients_equal_zeros_poles_gain(f):
    b, a = f.coefficients()
    zi = np.exp(-1j * W)
    h = np.polyval(b[::-1], zi) / np.polyval(a[::-1], zi)
    np.testing.assert_allclose(h, zpk_response(f), rtol=1e-9)


def test_leaky_integrator_matrices_are_the_papers():
    A, B, C = Filter.leaky(0.95, 0.3).unit_state_space()
    assert A.tolist() == [[0.95]] and B.tolist() == [1.0] and C.tolist() == [1.0]


@pytest.mark.parametrize("roots", tables.tt_iir_table(), ids=lambda r: f"{r.frame_rate_hz:g}Hz")
def test_integral_action_is_exact_in_float32(roots):
    """The pole at z = 1 of the paper's Tip/Tilt filters stays at 1 after rounding Lambda to float32."""
    A, _, _ = Filter.iir(roots.zeros, roots.poles, 1.0).unit_state_space()
    eig = np.linalg.eigvals(A.astype(np.float32).astype(np.float64))
    assert np.max(np.abs(eig)) == pytest.approx(1.0, abs=1e-12)
    # the other poles stay where the table puts them, to float32 accuracy
    others = sorted(e.real for e in eig if abs(e - 1) > 1e-9 and abs(e) > 1e-6)  # 0: input delay states
    np.testing.assert_allclose(others, sorted(p for p in roots.poles if p != 1.0), atol=2e-3)


def test_n_states_and_gain_independence():
    f = Filter.iir([0.1, 0.2, 0.3, 0.4], [0.1, 0.2, 0.3, 1.0], 0.5)
    assert f.n_states == 8
    A1, B1, C1 = f.unit_state_space()
    A2, B2, C2 = f.with_gain(2.0).unit_state_space()
    assert np.array_equal(A1, A2) and np.array_equal(B1, B2) and np.array_equal(C1, C2)


def test_invalid_filters():
    with pytest.raises(InputError, match="conjugate pairs"):
        Filter.iir([0.5 + 0.3j], [0.5], 1.0)
    with pytest.raises(InputError, match="at least one pole"):
        Filter.iir([0.5], [], 1.0)
    with pytest.raises(InputError, match="forgetting factor must be in"):
        Filter.leaky(1.2, 0.5)
    with pytest.raises(InputError, match="finite"):
        Filter.integrator(float("nan"))
    for roots in ([float("nan")], [float("inf")], [0.5 + float("nan") * 1j]):
        with pytest.raises(InputError, match="zeros and poles must be finite"):
            Filter.iir([], roots, 1.0)


@pytest.mark.parametrize("f", paper_filters())
def test_package_responses_state_space_equals_zeros_poles_gain(f):
    """The two representations the package offers (one object, one truth)."""
    np.testing.assert_allclose(f.state_space_frequency_response(W), f.frequency_response(W), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(f.frequency_response(W), zpk_response(f), rtol=1e-12)
