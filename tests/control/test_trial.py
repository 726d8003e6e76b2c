"""Trial-and-error helpers: the paper's gain groups and the smoothed minimum of a scan."""

import numpy as np
import pytest

from soulctl.control.trial import best_gain, gain_groups, scan_gains
from soulctl.errors import InputError


def test_groups_are_the_papers_three():
    assert [(n, s.start, s.stop) for n, s in gain_groups(500)] == [
        ("tip-tilt", 0, 2), ("modes 3-120", 2, 120), ("modes 121-500", 120, 500)]
    assert [s.stop for _, s in gain_groups(54)] == [2, 54]


def test_best_gain_is_the_vertex_of_the_parabola_not_the_best_sample():
    g = scan_gains(1.0, 8)
    merit = 3.0 + 5.0 * (g - 0.47) ** 2
    best = best_gain(g, merit)
    assert best == pytest.approx(0.47, abs=1e-9)
    assert best not in g


def test_best_gain_falls_back_to_the_best_sample():
    g = np.array([0.1, 0.2, 0.3, 0.4])
    assert best_gain(g, [1.0, 2.0, 3.0, 4.0]) == 0.1  # at the end of the scan
    assert best_gain(g, [3.0, 2.0, 1.0, 1.5]) == pytest.approx(0.3, abs=0.1)
    assert best_gain(g, [3.0, 1.0, 1.0, 0.5]) == 0.4
    assert best_gain(g, [5.0, np.nan, 1.0, 2.0]) == 0.3  # a diverged sequence's merit


def test_bad_scans_are_input_errors():
    with pytest.raises(InputError):
        scan_gains(0.0)
    with pytest.raises(InputError):
        best_gain([0.1, 0.2], [1.0, 2.0])
    with pytest.raises(InputError):
        best_gain([0.1, 0.2, 0.3], [np.nan] * 3)
