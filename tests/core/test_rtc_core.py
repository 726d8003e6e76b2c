"""RealTimeController: the C++ step against a plain numpy evaluation of the paper's RTC
equation, the batched replay against single steps, gain changes, structure and errors."""

import numpy as np
import pytest

from soulctl import _core
from soulctl._core import RealTimeController
from soulctl.control.filters import Filter
from soulctl.control.rtc import build_rtc

IIR_1700 = ([-0.310, 0.690, 0.698, 0.705], [0.042, 0.102, 0.954, 1.000])
IIR_750 = ([0.316, 0.316, 0.329, 0.329], [-0.461, 0.633, 0.720, 1.000])


def mixed_rtc(rng, n_slopes=60, n_commands=30, state_size=40):
    """Two IIR modes, leaky and pure integrators, an uncontrolled mode and unused states."""
    filters = [
        Filter.iir(*IIR_1700, gain=0.69),
        Filter.iir(*IIR_750, gain=0.8),
        *[Filter.leaky(rng.uniform(0.9, 1.0), rng.uniform(0.1, 0.6)) for _ in range(12)],
        Filter.integrator(0.3),
        None,
        Filter.leaky(0.95, 0.2),
    ]
    R = rng.normal(size=(len(filters) + 2, n_slopes))
    M = rng.normal(size=(n_commands, len(filters) + 2))
    return build_rtc(filters, R, M, state_size=state_size)


def numpy_rtc(mats, slopes, deltas, dtype=np.float32):
    """zeta(k) = Lambda zeta(k-1) + Delta Xi s(k); c(k) = Sigma zeta(k), plainly in numpy."""
    L, X, S = (np.asarray(m, np.float32).astype(dtype) for m in (mats.Lambda, mats.Xi, mats.Sigma))
    zeta = np.zeros(L.shape[0], dtype)
    out = []
    for s, d in zip(slopes, deltas):
        zeta = L @ zeta + np.asarray(d, np.float32).astype(dtype) * (X @ s.astype(dtype))
        out.append(S @ zeta)
    return np.array(out)


def assert_float32_accurate(got, mats, slopes, deltas):
    """'Equal to float32 accuracy': the C++ result is as close to a float64 evaluation of the same
    float32 matrices as numpy's own float32 evaluation is (integrator states accumulate rounding,
    so a fixed tolerance would be either too loose early or too tight late)."""
    exact = numpy_rtc(mats, slopes, deltas, dtype=np.float64)
    np32 = numpy_rtc(mats, slopes, deltas, dtype=np.float32)
    scale = np.max(np.abs(exact))
    err_np32 = np.max(np.abs(np32 - exact))
    err = np.max(np.abs(got - exact))
    assert err <= 4 * err_np32 + 1e-6 * scale, (err, err_np32, scale)


def assert_float32_close(a, b):
    scale = max(np.max(np.abs(b)), 1e-30)
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-4 * scale)


@pytest.mark.parametrize("n_threads", [1, 2, 3])
def test_step_equals_numpy_equation(n_threads):
    rng = np.random.default_rng(10)
    mats = mixed_rtc(rng)
    rtc = mats.controller(n_threads=n_threads)
    slopes = rng.normal(size=(200, mats.Xi.shape[1])).astype(np.float32)
    got = np.array([rtc.step(s) for s in slopes])
    assert_float32_accurate(got, mats, slopes, [mats.Delta] * len(slopes))
    assert np.all(np.isfinite(got)) and np.max(np.abs(got)) > 0


def test_run_equals_steps_with_changing_gains():
    rng = np.random.default_rng(11)
    mats = mixed_rtc(rng)
    slopes = rng.normal(size=(2500, mats.Xi.shape[1])).astype(np.float32)  # > one internal chunk
    gains = np.repeat(rng.uniform(0, 0.7, size=(5, mats.n_states)), 500, axis=0).astype(np.float32)
    stepped = mats.controller()
    one_by_one = []
    for s, g in zip(slopes, gains):
        stepped.set_state_gains(g)
        one_by_one.append(stepped.step(s))
    batched = mats.controller()
    replay = batched.run(slopes, state_gains=gains)
    assert_float32_close(replay, np.array(one_by_one))
    np.testing.assert_allclose(batched.state, stepped.state, rtol=1e-4, atol=1e-4 * np.max(np.abs(stepped.state)))
    assert_float32_accurate(replay, mats, slopes, gains)


def test_run_without_gains_uses_current_delta_and_continues_the_state():
    rng = np.random.default_rng(12)
    mats = mixed_rtc(rng)
    slopes = rng.normal(size=(300, mats.Xi.shape[1])).astype(np.float32)
    a = mats.controller()
    first = a.run(slopes[:100])
    second = a.run(slopes[100:])
    b = mats.controller()
    whole = b.run(slopes)
    assert_float32_close(np.vstack([first, second]), whole)


def test_gain_change_takes_effect_from_the_next_step():
    """Integrator on one mode: c(k) = c(k-1) + g(k) s(k); a new Delta never touches the past."""
    R = np.eye(1, 2)
    M = np.eye(1)
    mats = build_rtc([Filter.integrator(0.5)], R, M, state_size=1)
    rtc = mats.controller()
    s = np.array([1.0, 0.0], np.float32)
    assert rtc.step(s)[0] == pytest.approx(0.5)
    rtc.set_state_gains(np.array([0.2], np.float32))
    assert rtc.state[0] == pytest.approx(0.5)  # setting Delta changes nothing by itself
    assert rtc.step(s)[0] == pytest.approx(0.7)  # 0.5 + 0.2 * 1
    rtc.set_state_gains(np.array([0.0], np.float32))
    assert rtc.step(s)[0] == pytest.approx(0.7)  # zero gain: the integrator holds


def test_gain_change_on_iir_scales_only_new_inputs():
    """For the IIR realisation the stored past inputs keep the gain they entered with."""
    zeros, poles = IIR_1700
    R = np.eye(1, 1)
    mats = build_rtc([Filter.iir(zeros, poles, 1.0)], R, np.eye(1), state_size=8)
    rtc = mats.controller()
    impulse = np.array([1.0], np.float32)
    zero = np.array([0.0], np.float32)
    ref = mats.controller()
    rtc.step(impulse)
    ref.step(impulse)
    rtc.set_state_gains(np.full(8, 3.0, np.float32))
    # With no new input the response to the past impulse is unchanged by the new gain.
    for _ in range(20):
        np.testing.assert_allclose(rtc.step(zero), ref.step(zero), rtol=1e-6, atol=1e-7)


def test_reset_zeroes_the_state():
    rng = np.random.default_rng(13)
    mats = mixed_rtc(rng)
    rtc = mats.controller()
    s = rng.normal(size=mats.Xi.shape[1]).astype(np.float32)
    first = rtc.step(s)
    rtc.step(s)
    rtc.reset()
    assert np.all(rtc.state == 0)
    np.testing.assert_array_equal(rtc.step(s), first)


def test_structure_is_found():
    rng = np.random.default_rng(14)
    mats = mixed_rtc(rng)
    st = mats.controller().structure
    # 2 IIR blocks of 8; 14 one-state controllers + 40 - 30 = 10 unused states on the diagonal
    assert sorted(st["block_sizes"]) == [8, 8]
    assert st["diagonal_states"] == 40 - 16
    # Xi rows: 3 per IIR (w(k), g u(k) and the integrator y(k) take the input) + 14 integrators
    assert st["input_rows"] == 2 * 3 + 14
    # Sigma columns: the output state of each controlled mode
    assert st["output_states"] == 16


def test_sigma_and_xi_with_unexpected_dense_lambda_still_exact():
    """A Lambda that is not block-diagonal at all is handled as one dense block."""
    rng = np.random.default_rng(15)
    n, ns, nc = 12, 20, 7
    L = rng.normal(scale=0.2, size=(n, n))
    X = rng.normal(size=(n, ns))
    S = rng.normal(size=(nc, n))
    d = rng.uniform(0, 1, n).astype(np.float32)
    rtc = RealTimeController(L, X, S, n_threads=2)
    rtc.set_state_gains(d)
    assert rtc.structure["block_sizes"] == [n]
    slopes = rng.normal(size=(50, ns)).astype(np.float32)

    class Mats:  # the numpy reference takes the same three matrices
        Lambda, Xi, Sigma = L, X, S

    assert_float32_accurate(np.array([rtc.step(s) for s in slopes]), Mats, slopes, [d] * 50)


def test_errors_name_expected_and_given_shapes():
    rng = np.random.default_rng(16)
    mats = mixed_rtc(rng)
    rtc = mats.controller()
    with pytest.raises(ValueError, match=r"^slopes: expected shape \(60,\), got \(59,\)$"):
        rtc.step(np.zeros(59, np.float32))
    with pytest.raises(ValueError, match=r"^slopes: expected dtype float32, got float64$"):
        rtc.step(np.zeros(60))
    with pytest.raises(ValueError, match=r"^state_gains: expected shape \(40,\), got \(39,\)$"):
        rtc.set_state_gains(np.zeros(39, np.float32))
    with pytest.raises(ValueError, match=r"slopes: expected shape \(any, 60\), got \(5, 61\)"):
        rtc.run(np.zeros((5, 61), np.float32))
    with pytest.raises(ValueError, match=r"gains: expected shape \(5, 40\), got \(5, 39\)"):
        rtc.run(np.zeros((5, 60), np.float32), state_gains=np.zeros((5, 39), np.float32))
    with pytest.raises(ValueError, match=r"out: expected dtype float32"):
        rtc.step(np.zeros(60, np.float32), out=np.zeros(30))
    with pytest.raises(ValueError, match=r"Lambda must be square"):
        RealTimeController(np.zeros((3, 4)), np.zeros((3, 5)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"Xi must have shape \(3, n_slopes\), got \(4, 5\)"):
        RealTimeController(np.zeros((3, 3)), np.zeros((4, 5)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"Sigma must have shape \(n_commands, 3\), got \(2, 4\)"):
        RealTimeController(np.zeros((3, 3)), np.zeros((3, 5)), np.zeros((2, 4)))
    with pytest.raises(ValueError, match=r"Xi: expected dtype float32 or float64, got int64"):
        RealTimeController(np.zeros((3, 3)), np.zeros((3, 5), np.int64), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="finite"):
        RealTimeController(np.full((3, 3), np.nan), np.zeros((3, 5)), np.zeros((2, 3)))


def test_non_finite_gains_are_refused_and_leave_delta_unchanged():
    rng = np.random.default_rng(18)
    mats = mixed_rtc(rng)
    rtc = mats.controller()
    before = rtc.state_gains
    bad = before.copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match="state_gains: values must be finite"):
        rtc.set_state_gains(bad)
    np.testing.assert_array_equal(rtc.state_gains, before)
    per_step = np.tile(before, (4, 1))
    per_step[2, 0] = np.inf
    with pytest.raises(ValueError, match="state_gains: values must be finite"):
        rtc.run(np.zeros((4, 60), np.float32), state_gains=per_step)
    with pytest.raises(ValueError, match="out: expected a numpy array"):
        rtc.step(np.zeros(60, np.float32), out=[0.0] * 30)


def test_non_contiguous_slopes_are_accepted():
    rng = np.random.default_rng(17)
    mats = mixed_rtc(rng)
    big = rng.normal(size=(120,)).astype(np.float32)
    a, b = mats.controller(), mats.controller()
    np.testing.assert_array_equal(a.step(big[::2]), b.step(np.ascontiguousarray(big[::2])))


@pytest.mark.parametrize("n_threads", [-1, -5, 65, 1000, 2**40, -(2**70)])
def test_n_threads_outside_0_to_64_is_refused_not_clamped(n_threads):
    rng = np.random.default_rng(19)
    mats = mixed_rtc(rng)
    expected = rf"^n_threads: expected an integer in 0\.\.64 \(0 = automatic\), got {n_threads}$"
    with pytest.raises(ValueError, match=expected):
        RealTimeController(mats.Lambda, mats.Xi, mats.Sigma, n_threads=n_threads)
    with pytest.raises(ValueError, match=expected):  # the Python side passes it through
        mats.controller(n_threads=n_threads)


@pytest.mark.parametrize("n_threads, message", [(True, "bool"), (2.0, "float"), ("2", "str")])
def test_n_threads_must_be_an_integer(n_threads, message):
    with pytest.raises(TypeError, match=f"^n_threads: expected an integer, got {message}$"):
        RealTimeController(np.eye(2), np.eye(2), np.eye(2), n_threads=n_threads)


@pytest.mark.parametrize("n_threads", [0, 1, 2, 64, np.int64(3)])
def test_n_threads_in_range_is_accepted(n_threads):
    rng = np.random.default_rng(20)
    mats = mixed_rtc(rng)
    rtc = mats.controller(n_threads=n_threads)
    assert 1 <= rtc.n_threads <= max(1, int(n_threads) or 4)
    if not _core.openmp:
        assert rtc.n_threads == 1
    elif n_threads == 1:
        assert rtc.n_threads == 1
    slopes = rng.normal(size=(20, mats.Xi.shape[1])).astype(np.float32)
    assert_float32_accurate(np.array([rtc.step(s) for s in slopes]), mats, slopes, [mats.Delta] * 20)
