"""One rule for float inputs of the core: every float array given as a setting or as an input
of the controller must be finite; a NaN or infinity raises ValueError naming the argument and
the first bad position, and changes nothing.  Detector frames are data: non-finite pixels are
dark light, never an error."""

import re

import numpy as np
import pytest

from soulctl._core import RealTimeController, SlopeComputer
from soulctl.control.filters import Filter
from soulctl.control.rtc import build_rtc

BAD = [np.nan, np.inf, -np.inf]


def text(value):
    return "nan" if np.isnan(value) else ("inf" if value > 0 else "-inf")


def message(name, value, where):
    return "^" + re.escape(f"{name}: values must be finite, got {text(value)} at {where}") + "$"


def leaky_rtc(n_threads=0):
    """An IIR mode and leaky integrators: every state remembers the past, so a NaN would stay."""
    rng = np.random.default_rng(30)
    filters = [Filter.iir([-0.310, 0.690, 0.698, 0.705], [0.042, 0.102, 0.954, 1.000], gain=0.69)]
    filters += [Filter.leaky(0.95, 0.3) for _ in range(6)]
    mats = build_rtc(filters, rng.normal(size=(7, 20)), rng.normal(size=(9, 7)), state_size=16)
    return mats, rng


# --- RealTimeController ---------------------------------------------------------------------


@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("which", ["Lambda", "Xi", "Sigma"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_construction_matrices_must_be_finite(bad, which, dtype):
    mats = {"Lambda": np.eye(3, dtype=dtype), "Xi": np.ones((3, 5), dtype), "Sigma": np.ones((2, 3), dtype)}
    mats[which][1, 2] = bad
    with pytest.raises(ValueError, match=message(which, bad, "[1, 2]")):
        RealTimeController(mats["Lambda"], mats["Xi"], mats["Sigma"])


@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("n_threads", [1, 2])
def test_non_finite_slope_is_refused_and_does_not_poison_the_state(bad, n_threads):
    mats, rng = leaky_rtc()
    slopes = rng.normal(size=(30, 20)).astype(np.float32)
    rtc, clean = mats.controller(n_threads=n_threads), mats.controller(n_threads=n_threads)
    for s in slopes[:10]:
        rtc.step(s)
        clean.step(s)
    state, out = rtc.state, np.full(9, 7.0, np.float32)
    frame = slopes[10].copy()
    frame[13] = bad
    with pytest.raises(ValueError, match=message("slopes", bad, "index 13")):
        rtc.step(frame, out=out)
    np.testing.assert_array_equal(rtc.state, state)
    assert np.all(out == 7.0)  # out= untouched
    # The refused frame left no trace: the controller goes on exactly like one that never saw it.
    for s in slopes[11:]:
        np.testing.assert_array_equal(rtc.step(s), clean.step(s))
    assert np.all(np.isfinite(rtc.state))


@pytest.mark.parametrize("bad", BAD)
def test_run_checks_the_whole_block_before_the_first_step(bad):
    mats, rng = leaky_rtc()
    rtc = mats.controller()
    rtc.run(rng.normal(size=(5, 20)).astype(np.float32))
    state, gains = rtc.state, rtc.state_gains
    block = rng.normal(size=(8, 20)).astype(np.float32)
    block[6, 4] = bad  # late in the block: the first steps must not have run either
    with pytest.raises(ValueError, match=message("slopes", bad, "[6, 4]")):
        rtc.run(block)
    np.testing.assert_array_equal(rtc.state, state)
    per_step = np.tile(gains, (8, 1))
    per_step[5, 3] = bad
    with pytest.raises(ValueError, match=message("state_gains", bad, "[5, 3]")):
        rtc.run(np.zeros((8, 20), np.float32), state_gains=per_step)
    np.testing.assert_array_equal(rtc.state, state)
    np.testing.assert_array_equal(rtc.state_gains, gains)


@pytest.mark.parametrize("bad", BAD)
def test_set_state_gains_names_the_first_bad_value(bad):
    mats, _ = leaky_rtc()
    rtc = mats.controller()
    before = rtc.state_gains
    g = before.copy()
    g[[4, 9]] = bad
    with pytest.raises(ValueError, match=message("state_gains", bad, "index 4")):
        rtc.set_state_gains(g)
    np.testing.assert_array_equal(rtc.state_gains, before)


def test_finite_extremes_are_accepted():
    """The rule is finiteness, not a range: the largest float32 values pass the check."""
    big = np.finfo(np.float32).max
    rtc = RealTimeController(np.zeros((2, 2)), np.eye(2, 3), np.eye(2))
    rtc.set_state_gains(np.array([big, -big], np.float32))
    rtc.step(np.array([0.0, 0.0, -big], np.float32))
    np.testing.assert_array_equal(rtc.state, [0.0, 0.0])


# --- SlopeComputer --------------------------------------------------------------------------

SHAPE = (8, 8)


def pixel_map(n_sub=4):
    """As in test_slopes: four 2x2 pupil images in the four quadrants of an 8x8 frame."""
    pix = []
    for i in range(n_sub):
        r, c = divmod(i, 2)
        pix.append([(4 + r, 4 + c), (r, 4 + c), (4 + r, c), (r, c)])
    return np.array(pix, dtype=np.int32)


def frame_with_tilt():
    rng = np.random.default_rng(31)
    return rng.uniform(50, 100, SHAPE).astype(np.float32)


@pytest.mark.parametrize("bad", BAD)
def test_reference_must_be_finite_and_is_kept_when_refused(bad):
    sc = SlopeComputer(pixel_map(), SHAPE)
    frame = frame_with_tilt()
    ref = np.linspace(-0.1, 0.1, 8).astype(np.float32)
    sc.set_reference(ref)
    expected = sc.compute(frame).copy()
    bad_ref = ref.copy()
    bad_ref[3] = bad
    with pytest.raises(ValueError, match=message("reference", bad, "index 3")):
        sc.set_reference(bad_ref)
    assert sc.has_reference
    np.testing.assert_array_equal(sc.compute(frame), expected)
    fresh = SlopeComputer(pixel_map(), SHAPE)
    with pytest.raises(ValueError, match="reference: values must be finite"):
        fresh.set_reference(bad_ref)
    assert not fresh.has_reference


@pytest.mark.parametrize("bad", BAD)
@pytest.mark.parametrize("where", [(2, 5), (3, 3)], ids=["used pixel", "unused pixel"])
def test_background_must_be_finite_everywhere_and_is_kept_when_refused(bad, where):
    pix = pixel_map(1)  # uses (0, 0), (0, 4), (4, 0), (4, 4): (2, 5) and (3, 3) are not read
    sc = SlopeComputer(pix, SHAPE)
    frame = frame_with_tilt()
    bg = np.full(SHAPE, 10.0, np.float32)
    sc.set_background(bg)
    expected = sc.compute(frame).copy()
    bad_bg = bg.copy()
    bad_bg[where] = bad
    with pytest.raises(ValueError, match=message("background", bad, f"[{where[0]}, {where[1]}]")):
        sc.set_background(bad_bg)
    assert sc.has_background
    np.testing.assert_array_equal(sc.compute(frame), expected)


@pytest.mark.parametrize("bad", BAD)
def test_non_finite_pixel_darkens_its_subaperture_with_subaperture_normalisation(bad):
    pix = pixel_map()
    sc = SlopeComputer(pix, SHAPE, normalization="subaperture")
    frame = frame_with_tilt()
    good = sc.compute(frame).copy()
    frame[tuple(pix[2, 1])] = bad
    s = sc.compute(frame)
    assert sc.n_dark == 1 and not sc.flux_ok
    assert s[2] == 0.0 and s[6] == 0.0
    keep = [0, 1, 3, 4, 5, 7]
    np.testing.assert_array_equal(s[keep], good[keep])


@pytest.mark.parametrize("bad", BAD)
def test_non_finite_pixel_darkens_the_frame_with_global_normalisation(bad):
    pix = pixel_map()
    sc = SlopeComputer(pix, SHAPE)
    sc.set_reference(np.full(8, 0.2, np.float32))
    frame = frame_with_tilt()
    frame[tuple(pix[2, 1])] = bad
    s = sc.compute(frame)
    assert np.all(s == 0.0) and sc.n_dark == 4 and not sc.flux_ok


def test_non_finite_pixel_outside_the_subapertures_is_never_read():
    pix = pixel_map(1)
    sc = SlopeComputer(pix, SHAPE)
    frame = frame_with_tilt()
    expected = sc.compute(frame).copy()
    frame[3, 3] = np.nan
    np.testing.assert_array_equal(sc.compute(frame), expected)
    assert sc.flux_ok and sc.n_dark == 0


@pytest.mark.filterwarnings("error")
def test_float64_matrix_beyond_float32_range_is_refused():
    """Construction matrices are stored as float32: 1e39 cannot be, and is refused before the
    cast (no numpy overflow warning, which -W error would turn into another error)."""
    L = np.eye(2)
    L[0, 1] = 1e39
    with pytest.raises(ValueError, match=re.escape("Lambda: values must fit in float32 (|x| <= 3.4e38), got 1e+39 at [0, 1]")):
        RealTimeController(L, np.eye(2), np.eye(2))
