"""Calibration: push-pull interaction matrix, reconstructor, and the on-disk cache."""

import numpy as np
import pytest

from soulctl.errors import InputError
from soulctl.optics.cache import ArrayCache
from soulctl.optics.calibration import (
    CalibrationSetup,
    calibrate,
    calibration_sensor,
    mode_maps,
)
from soulctl.optics.pwfs import PyramidConfig

SMALL = PyramidConfig(binning=4, oversampling=1)


@pytest.fixture(scope="module")
def small(optics_cache):
    return calibrate(CalibrationSetup(SMALL, 54), optics_cache)


def test_interaction_matrix_is_the_derivative_of_the_slopes(small):
    """Push-pull columns equal a one-sided finite difference with a tiny push (the slopes are
    smooth around the reference), and Tip/Tilt land on sx/sy with the right signs."""
    sensor = calibration_sensor(SMALL)
    maps = mode_maps(small.basis.shapes(sensor.pupil), sensor.pupil)
    D = small.interaction_matrix
    assert D.shape == (2 * sensor.n_subapertures, 54)
    for i in (0, 7, 40):
        ds = (sensor.noiseless_slopes(maps[i : i + 1] * 1.0)[0] - sensor.noiseless_slopes(maps[i : i + 1] * 0.0)[0]) / 1.0
        np.testing.assert_allclose(ds, D[:, i], atol=0.03 * np.abs(D[:, i]).max())
    n = sensor.n_subapertures
    assert D[:n, 0].mean() > 0 and abs(D[n:, 0].mean()) < 0.05 * D[:n, 0].mean()
    assert D[n:, 1].mean() > 0 and abs(D[:n, 1].mean()) < 0.05 * D[n:, 1].mean()


def test_reconstructor_recovers_a_small_modal_wavefront(small):
    sensor = calibration_sensor(SMALL)
    shapes = small.basis.shapes(sensor.pupil)
    rng = np.random.default_rng(2)
    a = rng.normal(0, 2.0, 54)  # nm RMS per mode: ~15 nm in all, well inside the linear range
    opd = mode_maps((shapes @ a)[:, None], sensor.pupil)[0]
    estimate = small.reconstructor @ sensor.noiseless_slopes(opd[None])[0]
    np.testing.assert_allclose(estimate, a, atol=0.05 * np.abs(a).max())
    assert np.allclose(small.reconstructor @ small.interaction_matrix, np.eye(54), atol=1e-9)
    assert 1 < small.condition_number < 100


def test_cache_hit_is_identical_and_keys_follow_the_configuration(tmp_path):
    cache = ArrayCache(tmp_path)
    setup = CalibrationSetup(SMALL, 20)
    first = calibrate(setup, cache)
    second = calibrate(setup, cache)
    assert not first.from_cache and second.from_cache
    assert np.array_equal(first.interaction_matrix, second.interaction_matrix)
    assert np.array_equal(first.reconstructor, second.reconstructor)
    keys = {
        setup.key(),
        CalibrationSetup(SMALL, 21).key(),
        CalibrationSetup(PyramidConfig(binning=3, oversampling=1), 20).key(),
        CalibrationSetup(PyramidConfig(binning=4, oversampling=1, modulation_lambda_over_d=4.0), 20).key(),
        CalibrationSetup(SMALL, 20, push_nm=5.0).key(),
    }
    assert len(keys) == 5
    assert not list(tmp_path.glob(".soulctl-*"))  # no temporary files left behind


def test_a_corrupt_cache_entry_is_recomputed(tmp_path):
    cache = ArrayCache(tmp_path)
    setup = CalibrationSetup(SMALL, 10)
    good = calibrate(setup, cache)
    cache.path(setup.key()).write_bytes(b"half a file")
    again = calibrate(setup, cache)
    assert not again.from_cache
    assert np.array_equal(good.interaction_matrix, again.interaction_matrix)


def test_an_unwritable_cache_is_no_cache(tmp_path):
    """A sweep worker on another host gets the client's cache path: calibration still works."""
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    cal = calibrate(CalibrationSetup(SMALL, 5), ArrayCache(blocker / "cache"))
    assert not cal.from_cache and cal.interaction_matrix.shape[1] == 5


def test_no_cache_writes_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    calibrate(CalibrationSetup(SMALL, 5), ArrayCache(None))
    assert not list(tmp_path.iterdir())


def test_more_modes_than_the_mirror_has_is_an_input_error(optics_cache):
    with pytest.raises(InputError, match="modes must be in 2..671, got 700"):
        calibrate(CalibrationSetup(SMALL, 700), optics_cache)
    with pytest.raises(InputError):
        CalibrationSetup(SMALL, 10, push_nm=0.0)
