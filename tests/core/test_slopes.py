"""SlopeComputer: the quadrant formulas, normalisations, background/reference, dark frames
and argument errors, against a plain numpy evaluation of the documented formulas."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from soulctl._core import SlopeComputer

SHAPE = (8, 8)


def pixel_map(n_sub=4):
    """n_sub sub-apertures on an 8x8 frame: four 2x2 pupil images in the four quadrants,
    image 1 = (+x, +y) = high rows/high cols, 2 = (+x, -y), 3 = (-x, +y), 4 = (-x, -y)."""
    pix = []
    for i in range(n_sub):
        r, c = divmod(i, 2)
        pix.append([(4 + r, 4 + c), (r, 4 + c), (4 + r, c), (r, c)])
    return np.array(pix, dtype=np.int32)


def reference_slopes(frame, pixels, normalization="global", background=None, reference=None):
    f = frame.astype(np.float64) - (0 if background is None else background)
    I = np.stack([f[pixels[:, q, 0], pixels[:, q, 1]] for q in range(4)])  # (4, n)
    flux = I.sum(axis=0)
    sx = I[0] + I[1] - I[2] - I[3]
    sy = I[0] - I[1] + I[2] - I[3]
    norm = flux.mean() if normalization == "global" else flux
    s = np.concatenate([sx / norm, sy / norm])
    return s - (0 if reference is None else reference), flux


def test_quadrant_formulas_by_hand():
    pix = pixel_map(1)
    frame = np.zeros(SHAPE, np.float32)
    for q, value in enumerate([4.0, 3.0, 2.0, 1.0]):  # I1..I4
        frame[tuple(pix[0, q])] = value
    sc = SlopeComputer(pix, SHAPE)
    s = sc.compute(frame)
    # sx = (4+3-2-1)/10, sy = (4-3+2-1)/10 with N = 10 (one sub-aperture)
    np.testing.assert_allclose(s, [0.4, 0.2], rtol=1e-6)
    assert sc.total_flux == pytest.approx(10.0)
    assert sc.flux_ok and sc.n_dark == 0


def test_more_light_on_plus_x_images_gives_positive_sx():
    pix = pixel_map(4)
    frame = np.ones(SHAPE, np.float32)
    frame[:, 4:] = 3.0  # images 1 and 2 (+x) brighter
    s = SlopeComputer(pix, SHAPE).compute(frame)
    assert np.all(s[:4] > 0) and np.allclose(s[4:], 0)


@pytest.mark.parametrize("normalization", ["global", "subaperture"])
def test_matches_formula_on_random_frames(normalization):
    rng = np.random.default_rng(1)
    pix = pixel_map(4)
    frame = rng.uniform(1, 100, SHAPE).astype(np.float32)
    sc = SlopeComputer(pix, SHAPE, normalization=normalization)
    expected, flux = reference_slopes(frame, pix, normalization)
    np.testing.assert_allclose(sc.compute(frame), expected, rtol=2e-6, atol=1e-7)
    np.testing.assert_allclose(sc.subaperture_flux, flux, rtol=1e-6)
    assert sc.normalization == normalization


def test_global_and_subaperture_differ_when_fluxes_differ():
    rng = np.random.default_rng(2)
    pix = pixel_map(4)
    frame = rng.uniform(1, 100, SHAPE).astype(np.float32)
    g = SlopeComputer(pix, SHAPE, normalization="global").compute(frame)
    s = SlopeComputer(pix, SHAPE, normalization="subaperture").compute(frame)
    assert not np.allclose(g, s)


def test_uint16_and_float32_frames_agree():
    rng = np.random.default_rng(3)
    pix = pixel_map(4)
    frame16 = rng.integers(0, 65535, SHAPE).astype(np.uint16)
    sc = SlopeComputer(pix, SHAPE)
    np.testing.assert_allclose(sc.compute(frame16), sc.compute(frame16.astype(np.float32)), rtol=1e-6)
    np.testing.assert_allclose(sc.compute(frame16), reference_slopes(frame16, pix)[0], rtol=1e-5)


def test_background_and_reference():
    rng = np.random.default_rng(4)
    pix = pixel_map(4)
    frame = rng.uniform(50, 100, SHAPE).astype(np.float32)
    bg = rng.uniform(0, 10, SHAPE).astype(np.float32)
    ref = rng.normal(0, 0.1, 8).astype(np.float32)
    sc = SlopeComputer(pix, SHAPE)
    sc.set_background(bg)
    sc.set_reference(ref)
    assert sc.has_background and sc.has_reference
    expected, _ = reference_slopes(frame, pix, background=bg, reference=ref)
    np.testing.assert_allclose(sc.compute(frame), expected, rtol=1e-5, atol=1e-6)
    sc.clear_background()
    sc.clear_reference()
    np.testing.assert_allclose(sc.compute(frame), reference_slopes(frame, pix)[0], rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("fill", [0.0, -5.0, np.nan, np.inf])
@pytest.mark.parametrize("normalization", ["global", "subaperture"])
def test_dark_or_bad_frame_gives_zeros_and_a_flag(fill, normalization):
    pix = pixel_map(4)
    sc = SlopeComputer(pix, SHAPE, normalization=normalization)
    sc.set_reference(np.full(8, 0.3, np.float32))
    s = sc.compute(np.full(SHAPE, fill, np.float32))
    assert np.all(s == 0.0)
    assert not sc.flux_ok and sc.n_dark == 4


def test_background_equal_to_frame_is_dark():
    pix = pixel_map(4)
    frame = np.full(SHAPE, 7.0, np.float32)
    sc = SlopeComputer(pix, SHAPE)
    sc.set_background(frame)
    assert np.all(sc.compute(frame) == 0) and not sc.flux_ok


def test_subaperture_normalisation_zeroes_only_the_dark_subaperture():
    pix = pixel_map(4)
    frame = np.full(SHAPE, 5.0, np.float32)
    for q in range(4):
        frame[tuple(pix[2, q])] = 0.0
    frame[tuple(pix[0, 0])] = 9.0
    sc = SlopeComputer(pix, SHAPE, normalization="subaperture")
    s = sc.compute(frame)
    assert sc.n_dark == 1 and not sc.flux_ok
    assert s[2] == 0.0 and s[6] == 0.0
    assert s[0] == pytest.approx(4.0 / 24.0)
    assert np.all(np.isfinite(s))


@settings(max_examples=200, deadline=None)
@given(hnp.arrays(np.float32, SHAPE, elements=st.floats(-1e4, 1e4, width=32)), st.sampled_from(["global", "subaperture"]))
def test_never_nan_or_inf(frame, normalization):
    sc = SlopeComputer(pixel_map(4), SHAPE, normalization=normalization)
    s = sc.compute(frame)
    assert np.all(np.isfinite(s))
    if sc.flux_ok and normalization == "global" and abs(sc.total_flux) > 1e-2:
        expected, _ = reference_slopes(frame, pixel_map(4))
        np.testing.assert_allclose(s, expected, rtol=1e-3, atol=1e-3 * np.max(np.abs(expected)))


def test_out_array_is_filled_in_place():
    pix = pixel_map(4)
    rng = np.random.default_rng(5)
    frame = rng.uniform(1, 100, SHAPE).astype(np.float32)
    out = np.full(8, np.nan, np.float32)
    res = SlopeComputer(pix, SHAPE).compute(frame, out=out)
    assert np.shares_memory(res, out)
    np.testing.assert_allclose(out, reference_slopes(frame, pix)[0], rtol=2e-6, atol=1e-7)
    with pytest.raises(ValueError, match="out: expected a numpy array"):
        SlopeComputer(pix, SHAPE).compute(frame, out=[0.0] * 8)  # would be a temporary, never seen


@pytest.mark.parametrize("normalization", ["global", "subaperture"])
def test_overflowing_slopes_are_zero_and_flagged(normalization):
    """Negative pixels can make |dx| exceed a tiny flux: the slopes overflow, so the frame (global)
    or the sub-aperture (own flux) is unusable, never inf."""
    pix = pixel_map(2)
    frame = np.zeros(SHAPE, np.float32)
    frame[tuple(pix[0, 0])], frame[tuple(pix[0, 2])] = 1e4, -1e4  # sub-aperture 0: dx = 2e4, flux 0
    frame[tuple(pix[1, 0])] = 1e-35  # sub-aperture 1: a tiny flux
    frame[tuple(pix[0, 1])] = 1e-35
    sc = SlopeComputer(pix, SHAPE, normalization=normalization)
    s = sc.compute(frame)
    assert np.all(np.isfinite(s)) and not sc.flux_ok
    if normalization == "global":
        assert np.all(s == 0) and sc.n_dark == 2


@pytest.mark.parametrize(
    "frame, message",
    [
        (np.ones(SHAPE, np.float64), "frame: expected dtype float32 or uint16, got float64"),
        (np.ones((8, 9), np.float32), "frame: expected shape (8, 8), got (8, 9)"),
        (np.ones(64, np.uint16), "frame: expected shape (8, 8), got (64,)"),
    ],
)
def test_bad_frame_is_a_value_error_naming_expected_and_given(frame, message):
    sc = SlopeComputer(pixel_map(4), SHAPE)
    with pytest.raises(ValueError) as e:
        sc.compute(frame)
    assert str(e.value) == message


def test_frames_beyond_32_bit_indexing_are_refused():
    pix = np.array([[[46340, 46340], [0, 1], [1, 0], [1, 1]]])
    with pytest.raises(ValueError, match="more than 2\\^31-1 pixels"):
        SlopeComputer(pix, (46341, 46341))
    with pytest.raises(ValueError, match=r"pixel \(1099511627776, 0\) of sub-aperture 0 is outside"):
        SlopeComputer(np.array([[[2**40, 0], [0, 1], [1, 0], [1, 1]]]), SHAPE)


def test_bad_construction_and_arguments():
    with pytest.raises(ValueError, match=r"outside the frame of shape \(8, 8\)"):
        SlopeComputer(pixel_map(4) + 5, SHAPE)
    with pytest.raises(ValueError, match=r"pixels: expected shape \(any, 4, 2\), got \(4, 3, 2\)"):
        SlopeComputer(pixel_map(4)[:, :3], SHAPE)
    with pytest.raises(ValueError, match="integer array"):
        SlopeComputer(pixel_map(4).astype(float), SHAPE)
    with pytest.raises(ValueError, match="normalization"):
        SlopeComputer(pixel_map(4), SHAPE, normalization="local")
    sc = SlopeComputer(pixel_map(4), SHAPE)
    with pytest.raises(ValueError, match=r"reference: expected shape \(8,\), got \(7,\)"):
        sc.set_reference(np.zeros(7, np.float32))
    with pytest.raises(ValueError, match=r"out: expected shape \(8,\), got \(9,\)"):
        sc.compute(np.ones(SHAPE, np.float32), out=np.empty(9, np.float32))
    with pytest.raises(ValueError, match="background: expected dtype float32"):
        sc.set_background(np.ones(SHAPE, np.uint16))
