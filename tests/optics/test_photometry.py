"""Detected photons per sub-aperture per frame against the figures quoted in the paper."""

import pytest

from soulctl.optics.photometry import WfsPhotometry


@pytest.mark.parametrize(
    "mag, binning, rate, paper, tolerance",
    [
        (9.7, 1, 1700, 20, 0.15),  # on-sky IIR tests, 40x40
        (9.4, 1, 1700, 25, 0.15),  # MGM with IIR, July 2020
        (13.0, 2, 980, 6, 0.20),  # MGM on R13, 20x20
        (16.5, 4, 390, 2, 0.40),  # MGM on R16.5, 10x10 ("2" is one significant figure)
    ],
)
def test_photons_match_the_papers_figures(mag, binning, rate, paper, tolerance):
    ph = WfsPhotometry.from_table().photons_per_frame(mag, binning, rate)
    assert ph == pytest.approx(paper, rel=tolerance)


def test_r10_9_on_sky_figure_is_about_twice_lower_than_the_zero_point_gives():
    """The paper's R10.9 night (1212 Hz, 40x40) reports 5 ph/sa/frame; the zero point that fits
    its other four figures (within 15-40 %) gives ~9.5.  Recorded, not fitted (docs/physics.md)."""
    ph = WfsPhotometry.from_table().photons_per_frame(10.9, 1, 1212)
    assert 1.6 < ph / 5 < 2.2


def test_zero_point_per_square_metre_and_inverse():
    p = WfsPhotometry.from_table()
    assert p.zero_point_ph_s_m2 == pytest.approx(6.26e9, rel=0.01)
    assert p.magnitude(p.photons_per_frame(12.3, 2, 800), 2, 800) == pytest.approx(12.3)
