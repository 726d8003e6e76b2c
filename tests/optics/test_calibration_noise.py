"""The interaction matrix as measured.  At a finite flux its error has the variance the
slope noise predicts, sigma_s^2 / (2 frames a^2), and the loop run with it loses Strehl as the
calibration source dims (at 1e9 photons per frame it is the noiseless loop).  Measured around a
residual it carries the pyramid's optical gains there, so a loop at better seeing than the
calibration's is overdriven by gamma_loop / gamma_cal."""

import dataclasses

import numpy as np
import pytest

from soulctl.errors import InputError
from soulctl.loop.run import calibration_for, run
from soulctl.observation import observation_for_magnitude
from soulctl.optics.calibration_noise import CalibrationNoise, measured_calibration
from soulctl.optics.detector import Detector
from soulctl.optics.optical_gains import CorrectionLevel, optical_gains
from soulctl.optics.pwfs import Pyramid
from soulctl.optics.sensor import WavefrontSensor
from soulctl.run_config import RunConfig

OBS = dataclasses.replace(observation_for_magnitude(17), magnitude_r=11.0)
BASE = RunConfig(observation=OBS, duration_s=1.0, oversampling=1, wfs_field_arcsec=0.0).with_values(
    {"atmosphere.seeing_arcsec": 0.6, "ncpa.rms_nm": 0.0}
)  # the term alone


@pytest.fixture(scope="module")
def calibration(optics_cache):
    return calibration_for(BASE.request(), optics_cache)


@pytest.mark.parametrize("frames", [1, 4])
def test_the_matrix_error_is_the_slope_noise_over_the_push(calibration, frames):
    photons = 1e4
    measured = measured_calibration(calibration, CalibrationNoise(photons_per_frame=photons, frames=frames))
    error = measured.interaction_matrix - calibration.interaction_matrix
    sensor = WavefrontSensor(Pyramid(calibration.setup.pyramid), Detector(), photons)
    rng = np.random.default_rng(5)
    reads = [sensor.slopes_of_frame(sensor.detector.read(sensor.pyramid.reference_intensity, photons, rng)) for _ in range(400)]
    predicted = np.var(reads, axis=0).mean() / (2 * frames * calibration.setup.push_nm**2)
    assert error.var() == pytest.approx(predicted, rel=0.05)
    assert abs(error.mean()) < 0.05 * error.std()  # noise, no bias
    np.testing.assert_allclose(measured.reconstructor @ measured.interaction_matrix, np.eye(54), atol=1e-8)


def test_the_loop_loses_strehl_as_the_calibration_source_dims(optics_cache):
    strehl = {}
    for photons in (0.0, 1e9, 1e5):
        result = run(dataclasses.replace(BASE, calibration=CalibrationNoise(photons_per_frame=photons)).request(), optics_cache)
        assert result.diverged_at is None
        strehl[photons] = result.metrics.strehl
    assert strehl[1e9] == pytest.approx(strehl[0.0], abs=0.005)  # measured 0.477 / 0.476
    assert strehl[1e5] < strehl[0.0] - 0.1  # measured 0.222


def _projected_gains(measured, calibration):
    D0 = calibration.interaction_matrix
    return np.sum(measured.interaction_matrix * D0, axis=0) / np.sum(D0**2, axis=0)


def test_a_matrix_measured_around_a_residual_carries_the_optical_gains(calibration):
    gamma = {s: _projected_gains(measured_calibration(calibration, CalibrationNoise(seeing_arcsec=s)), calibration) for s in (0.6, 1.0)}
    table = optical_gains(calibration, CorrectionLevel(0.6), seed=7).gains  # other residual realisations
    assert np.mean(gamma[0.6]) == pytest.approx(np.mean(table), rel=0.1)  # measured 0.36 / 0.38
    assert np.mean(gamma[1.0]) < 0.6 * np.mean(gamma[0.6])  # measured 0.14 / 0.36
    assert np.all(gamma[0.6] < 0.6)


def test_a_matrix_measured_at_worse_seeing_overdrives_the_loop(optics_cache):
    configs = {s: dataclasses.replace(BASE, calibration=CalibrationNoise(seeing_arcsec=s)) for s in (0.0, 0.6, 1.0)}
    result = {s: run(c.request(), optics_cache) for s, c in configs.items()}
    assert result[0.0].diverged_at is None and result[0.6].diverged_at is None
    assert result[0.6].metrics.strehl >= result[0.0].metrics.strehl - 0.01  # measured 0.479 / 0.476
    assert result[1.0].diverged_at is not None  # every gain x gamma(0.6) / gamma(1.0) ~ 2.6


@pytest.mark.parametrize("field, value", [("photons_per_frame", 0.5), ("frames", 0), ("seed", -2), ("seeing_arcsec", 0.01)])
def test_out_of_range_values_are_refused_naming_the_field(field, value):
    with pytest.raises(InputError, match=f"calibration.{field}"):
        CalibrationNoise(**{field: value})
