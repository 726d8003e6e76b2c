"""The LBT pupil: geometry against the published figures."""

import numpy as np
import pytest

from soulctl.errors import InputError
from soulctl.optics.pupil import LBT_DIAMETER_M, LBT_OBSTRUCTION, Pupil


def test_area_is_the_annulus_of_8222_mm_with_11_percent_obstruction():
    p = Pupil(200)
    area = p.n_valid * p.pixel_scale_m**2
    expected = np.pi / 4 * LBT_DIAMETER_M**2 * (1 - LBT_OBSTRUCTION**2)
    assert area == pytest.approx(expected, rel=0.01)


def test_mask_is_symmetric_and_has_a_hole():
    m = Pupil(64).mask
    assert np.array_equal(m, m[::-1]) and np.array_equal(m, m[:, ::-1]) and np.array_equal(m, m.T)
    assert not m[31:33, 31:33].any()


def test_tilt_ramps_are_orthonormal_and_piston_free():
    tip, tilt = Pupil(64).tilt()
    assert np.mean(tip) == pytest.approx(0, abs=1e-12)
    assert np.mean(tip**2) == pytest.approx(1) and np.mean(tilt**2) == pytest.approx(1)
    assert np.mean(tip * tilt) == pytest.approx(0, abs=1e-12)


@pytest.mark.parametrize("kwargs", [{"n_pixels": 4}, {"n_pixels": 64, "diameter_m": 0}, {"n_pixels": 64, "obstruction": 1.0}])
def test_bad_geometry_is_an_input_error(kwargs):
    with pytest.raises(InputError):
        Pupil(**kwargs)


def test_a_resampler_carries_an_opd_onto_a_finer_pupil():
    """A constant stays itself; a tilt stays a tilt inside the pupil (at the rim and around the
    central obstruction, whose finer pixels reach beyond the coarse pixels' centres, within one
    coarse step); a batch is its maps'."""
    from soulctl.optics.pupil import PupilResampler

    coarse, fine = Pupil(80), Pupil(120)
    r = PupilResampler(coarse, fine)
    np.testing.assert_allclose(r(np.full((80, 80), 7.0, dtype=np.float32))[fine.mask], 7.0, rtol=1e-6)
    x = (np.arange(80) + 0.5 - 40) * coarse.pixel_scale_m
    ramp = np.tile(x, (80, 1)) * coarse.mask
    xf = np.tile((np.arange(120) + 0.5 - 60) * fine.pixel_scale_m, (120, 1))
    error = np.abs(r(ramp.astype(np.float32)) - xf)[fine.mask] / coarse.pixel_scale_m
    assert error.max() < 1.0 and np.sqrt(np.mean(error**2)) < 0.05
    radius = np.hypot(xf, xf.T)[fine.mask] / coarse.diameter_m
    inner = (radius > 0.12) & (radius < 0.45)  # away from the rim and the central obstruction's edge
    assert error[inner].max() < 0.01  # the cubic spline carries a little of the edges inwards
    batch = np.stack([ramp, 2 * ramp]).astype(np.float32)
    np.testing.assert_allclose(r(batch)[1], 2 * r(batch[0]), rtol=1e-5, atol=1e-7)
    with pytest.raises(InputError):
        PupilResampler(fine, coarse)
