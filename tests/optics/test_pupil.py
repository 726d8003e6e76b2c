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
