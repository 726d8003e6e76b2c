"""The optimisers' model of the Tip/Tilt POL (``loop.optimize.noise_aware_gains``): each axis
with its own vibration lines."""

import numpy as np
import pytest

from soulctl.control.gains import LoopGains
from soulctl.disturbance.vibrations import VibrationLine, VibrationSpectrum
from soulctl.loop.gain_policy import noise_aware_gains
from soulctl.observation import observation_for_magnitude
from soulctl.optics.atmosphere import AtmosphereConfig

OBS = observation_for_magnitude(14.5)


def tip_tilt_gains(tip_mas: float, tilt_mas: float) -> np.ndarray:
    lines = VibrationSpectrum((VibrationLine(13.0, 0.02, tip_mas, tilt_mas),))
    basis_variance = np.full(4, 1e-3)
    g = noise_aware_gains(
        OBS,
        None,
        LoopGains(0.3, 0.3, 0.3).forgetting,
        np.ones(4),
        basis_variance,
        AtmosphereConfig.lbt_default(0.6),
        np.full(4, 80.0),
        lines,
        nm_per_mas=30.0,
        every_mode=True,
    )
    return g[:2]


def test_a_line_on_one_axis_raises_that_axis_gain_only():
    """A strong 13 Hz line on Tip alone calls for a higher Tip gain than Tilt's; on Tilt alone the
    reverse, by as much (the axes differ by their lines only); on both, equal gains.  With the
    lines' mean on both axes (the earlier model) every case gave Tip and Tilt one gain."""
    tip_only, tilt_only, both = tip_tilt_gains(20.0, 0.0), tip_tilt_gains(0.0, 20.0), tip_tilt_gains(20.0, 20.0)
    assert tip_only[0] > 1.2 * tip_only[1]
    assert tilt_only[1] == pytest.approx(tip_only[0], rel=1e-9) and tilt_only[0] == pytest.approx(tip_only[1], rel=1e-9)
    assert both[0] == pytest.approx(both[1], rel=1e-9)
    assert both[0] >= tip_only[0] - 1e-9  # the line's power raises the gain; the other axis's does not lower it


def test_tilts_gain_follows_its_own_line_only():
    """Tilt's gain with a line on Tip only is Tilt's gain with no line at all."""
    tip_only, none = tip_tilt_gains(20.0, 0.0), tip_tilt_gains(0.0, 0.0)
    assert tip_only[1] == pytest.approx(none[1], rel=1e-9)
    assert tip_only[0] > none[0]
