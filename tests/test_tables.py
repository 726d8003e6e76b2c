"""The paper's tables as shipped: consistency with the paper's text."""

import pytest

from soulctl import tables
from soulctl.errors import InputError
from soulctl.observation import BINNINGS


def test_magnitude_rows_are_contiguous_and_match_the_paper():
    bands = tables.magnitude_table()
    assert [b.r_max for b in bands] == [10.5, 12.7, 14.5, 16.5, 18.5]
    assert all(a.r_max == b.r_min for a, b in zip(bands, bands[1:]))
    assert [(b.binning, b.subapertures, b.modes) for b in bands] == [(1, 40, 500), (1, 40, 500), (2, 20, 250), (3, 13, 90), (4, 10, 54)]
    assert all(b.modulation_lambda_over_d == 3 for b in bands)
    assert all(b.frame_rate_max_hz >= b.frame_rate_min_hz for b in bands)
    assert all(BINNINGS[b.binning] == b.subapertures for b in bands)


@pytest.mark.parametrize("mag, binning", [(0.0, 1), (10.5, 1), (10.51, 1), (12.7, 1), (12.71, 2), (16.5, 3), (18.5, 4)])
def test_band_edges_follow_r_min_lt_R_le_r_max(mag, binning):
    assert tables.band_for_magnitude(mag, tables.magnitude_table()).binning == binning


@pytest.mark.parametrize("mag", [-0.1, 18.51, 25])
def test_outside_the_table_names_the_range(mag):
    with pytest.raises(InputError, match=r"accepted range 0 <= R <= 18.5"):
        tables.band_for_magnitude(mag, tables.magnitude_table())


def test_roots_table_has_the_four_rates_with_integral_action():
    roots = tables.tt_iir_table()
    assert [r.frame_rate_hz for r in roots] == [750, 1000, 1350, 1700]
    assert all(len(r.zeros) == 4 and len(r.poles) == 4 and r.poles[-1] == 1.0 for r in roots)
    assert roots[-1].zeros[0] == -0.310 and roots[0].poles[0] == -0.461


def test_unknown_delay_model():
    with pytest.raises(InputError, match="accepted flao, soul"):
        tables.delay_terms("keck")
