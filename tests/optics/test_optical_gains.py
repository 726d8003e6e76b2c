"""Optical gains of the pyramid in partial correction: <= 1, falling with the residual,
closer to 1 with more modulation (Esposito et al. 2001; Deo et al. 2019)."""

import numpy as np
import pytest

from soulctl.errors import InputError
from soulctl.optics.calibration import CalibrationSetup, calibrate
from soulctl.optics.optical_gains import CorrectionLevel, optical_gains, read_optical_gains
from soulctl.optics.pwfs import PyramidConfig


def gains(modulation: float, seeing: float, cache):
    setup = CalibrationSetup(PyramidConfig(binning=4, oversampling=1, modulation_lambda_over_d=modulation), 54)
    cal = calibrate(setup, cache)
    return optical_gains(cal, CorrectionLevel(seeing_arcsec=seeing), n_screens=2, seed=4)


@pytest.fixture(scope="module")
def tables(optics_cache):
    return {(m, s): gains(m, s, optics_cache) for m in (2.0, 5.0) for s in (0.5, 0.8, 1.2)}


def test_optical_gains_are_at_most_one(tables):
    for t in tables.values():
        assert np.all(t.gains <= 1.0) and np.all(t.gains > 0)


def test_optical_gains_fall_as_the_residual_grows(tables):
    for m in (2.0, 5.0):
        residual = [tables[m, s].residual_nm for s in (0.5, 0.8, 1.2)]
        mean_gain = [tables[m, s].gains.mean() for s in (0.5, 0.8, 1.2)]
        assert residual[0] < residual[1] < residual[2]
        assert mean_gain[0] > mean_gain[1] > mean_gain[2]


def test_more_modulation_keeps_the_optical_gains_closer_to_one(tables):
    for s in (0.5, 0.8, 1.2):
        assert tables[5.0, s].gains.mean() > tables[2.0, s].gains.mean()


def test_no_residual_gives_unit_optical_gains(optics_cache):
    """With the controlled modes left whole-corrected and a tiny seeing, the sensor sees an
    almost flat wavefront: gains ~ 1 (a check of the estimator itself)."""
    t = gains(3.0, 0.05, optics_cache)
    np.testing.assert_allclose(t.gains, 1.0, atol=0.03)


def test_table_round_trips_through_csv(tmp_path, optics_cache):
    t = gains(3.0, 0.8, optics_cache)
    path = tmp_path / "og.csv"
    t.write_csv(path)
    text = path.read_text()
    assert "seeing_arcsec = 0.8" in text and "binning = 4" in text
    np.testing.assert_allclose(read_optical_gains(path), t.gains, atol=1e-5)


def test_bad_correction_levels_and_tables_are_input_errors(tmp_path):
    for kwargs in ({"seeing_arcsec": 0.0}, {"L0_m": -1.0}, {"controlled_fraction": 2.0}):
        with pytest.raises(InputError):
            CorrectionLevel(**kwargs)
    bad = tmp_path / "bad.csv"
    bad.write_text("mode,optical_gain,spread\n1,0.5,0\n3,0.4,0\n")
    with pytest.raises(InputError, match="modes 1..N"):
        read_optical_gains(bad)
