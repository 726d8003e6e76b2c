"""Trial-and-error helpers: the paper's gain groups and the smoothed minimum of a scan."""

import numpy as np
import pytest

from soulctl.control.trial import best_gain, chosen_gain, merit_scatter, scan_around, scan_gains
from soulctl.errors import InputError


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


def test_scan_around_is_geometric_and_holds_the_centre():
    g = scan_around(0.3, 2.0, 3.0, 8)
    assert g[0] == pytest.approx(0.1) and g[-1] == pytest.approx(0.9) and 0.3 in g and len(g) == 9
    assert np.allclose(np.diff(np.log(np.delete(g, np.flatnonzero(g == 0.3)))), np.log(9) / 7)
    capped = scan_around(0.3, 0.5, 3.0, 8)
    assert capped.max() == pytest.approx(0.5) and 0.3 in capped
    with pytest.raises(InputError):
        scan_around(0.0, 1.0)


def test_merit_scatter_ignores_a_trend_and_measures_the_noise():
    rng = np.random.default_rng(3)
    g = np.linspace(0.1, 1.0, 2000)
    m = 50 + 40 * g + rng.normal(0, 2.0, g.size)  # the trend moves the merit by 40, the noise by 2
    assert merit_scatter(m) == pytest.approx(2.0 * np.sqrt(2), rel=0.05)  # of a difference of two sequences
    assert merit_scatter([1.0, np.inf, 2.0]) == 0.0


def test_the_incumbent_stays_unless_beaten_by_more_than_the_scatter():
    g = scan_around(0.5, 2.0, 3.0, 8)
    rng = np.random.default_rng(0)
    flat = 80 + rng.normal(0, 4.0, g.size)  # a trendless scan: its minimum is a fluctuation
    assert chosen_gain(g, flat, 0.5) == 0.5
    assert chosen_gain(g, flat, None) == best_gain(g, flat) != 0.5
    bowl = 80 + 200 * (g - 1.1) ** 2 + rng.normal(0, 1.0, g.size)  # a real optimum far from 0.5
    assert chosen_gain(g, bowl, 0.5) == best_gain(g, bowl) > 0.8
    assert chosen_gain(g, bowl, 0.37) == best_gain(g, bowl)  # an incumbent not in the scan
