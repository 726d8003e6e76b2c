"""Mis-registration of the adaptive secondary on the pyramid: the transform of the actuator
positions, the influence functions that move with it (their centroids land where the transform
puts the actuators), the identity that changes nothing, and the closed loop's residual that
grows with the shift while the calibration stays the registered one."""

import dataclasses

import numpy as np
import pytest

from soulctl.errors import InputError
from soulctl.loop.run import run
from soulctl.loop.stages import Mirror
from soulctl.observation import observation_for_magnitude
from soulctl.optics.asm import INFLUENCES, AsmGeometry, thin_plate_cardinals
from soulctl.optics.cache import ArrayCache
from soulctl.optics.calibration import CalibrationSetup, calibrate, moved_mirror_response
from soulctl.optics.pupil import Pupil
from soulctl.optics.pwfs import Pyramid, PyramidConfig
from soulctl.optics.registration import Misregistration
from soulctl.run_config import RunConfig


def test_the_transform_shifts_in_pitches_rotates_and_magnifies():
    p = np.array([[1.0, 0.0], [0.0, 2.0]])
    assert Misregistration().is_identity and not Misregistration(rotation_deg=0.1).is_identity
    np.testing.assert_allclose(Misregistration().positions(p, 0.3), p)
    np.testing.assert_allclose(Misregistration(shift_x_pitch=0.5, shift_y_pitch=-1).positions(p, 0.3), p + [0.15, -0.3])
    c, s = np.cos(np.deg2rad(10)), np.sin(np.deg2rad(10))  # counter-clockwise
    np.testing.assert_allclose(Misregistration(rotation_deg=10).positions(p, 0.3), [[c, s], [-2 * s, 2 * c]], atol=1e-12)
    m = Misregistration(magnification=1.1)
    np.testing.assert_allclose(m.positions(p, 0.3), 1.1 * p)
    assert m.pitch(0.3) == pytest.approx(0.33)


@pytest.mark.parametrize(
    "field, value", [("shift_x_pitch", 2.5), ("rotation_deg", -11.0), ("magnification", 0.5), ("shift_y_pitch", np.nan)]
)
def test_out_of_range_values_are_refused_naming_the_field(field, value):
    with pytest.raises(InputError, match=f"misregistration.{field}"):
        Misregistration(**{field: value})


def test_the_influence_functions_move_where_the_transform_puts_the_actuators():
    """Centroids of the (Gaussian, symmetric) influence functions of actuators well inside the
    pupil (2.5 pitches from both edges) against the transformed positions: within 1 % of a
    pitch."""
    geometry, pupil = AsmGeometry(influence="gaussian"), Pupil(80)
    moved = Misregistration(shift_x_pitch=0.37, shift_y_pitch=-0.21, rotation_deg=3.0, magnification=1.02)
    F = geometry.sparse_influence_functions(pupil, registration=moved).toarray()
    x, y = pupil.coordinates()
    target = moved.positions(geometry.positions(), geometry.pitch_m)
    r = np.hypot(*target.T)
    R, pitch = geometry.diameter_m / 2, geometry.pitch_m
    inside = (r < R - 2.5 * pitch * 1.02) & (r > geometry.obstruction * R + 2.5 * pitch * 1.02)
    assert inside.sum() > 150
    w = F[:, inside]
    centroid = np.stack([x @ w, y @ w], axis=1) / w.sum(axis=0)[:, None]
    assert np.max(np.hypot(*(centroid - target[inside]).T)) < 0.01 * pitch
    nominal = geometry.sparse_influence_functions(pupil).toarray()
    assert np.abs(F - nominal).max() > 0.5  # the functions did move


def _nominal_functions_at(geometry: AsmGeometry, points: np.ndarray) -> np.ndarray:
    """The unmoved mirror's influence functions at arbitrary points (m)."""
    p, pitch = geometry.positions(), geometry.pitch_m
    if geometry.influence == "thin-plate":
        return thin_plate_cardinals(points, p, pitch)
    d2 = ((points[:, None, :] - p[None, :, :]) ** 2).sum(axis=2)
    return np.exp(np.log(geometry.coupling) * d2 / pitch**2)


@pytest.mark.parametrize("influence", INFLUENCES)
def test_a_moved_mirror_is_the_nominal_one_carried_by_the_transform(influence):
    """F'(T x) = F(x) for both influence models: the moved functions at a pixel are the nominal
    ones at the pixel's inverse-transformed position (to the sparse matrix's 1e-4 floor); the
    thin-plate cardinals are invariant under a similarity transform, and the Gaussian's width
    scales with the magnification."""
    geometry, pupil = AsmGeometry(influence=influence), Pupil(40)
    moved = Misregistration(shift_x_pitch=0.37, shift_y_pitch=-0.21, rotation_deg=3.0, magnification=1.02)
    F = geometry.sparse_influence_functions(pupil, registration=moved).toarray()
    x, y = pupil.coordinates()
    a = np.deg2rad(moved.rotation_deg)
    shift = np.array([moved.shift_x_pitch, moved.shift_y_pitch]) * geometry.pitch_m
    back = (np.stack([x, y], axis=1) - shift) @ np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) / moved.magnification
    assert np.abs(F - _nominal_functions_at(geometry, back)).max() <= 1.01e-4
    assert np.abs(F - geometry.sparse_influence_functions(pupil).toarray()).max() > 0.5


@pytest.fixture(scope="module")
def calibration(optics_cache):
    return calibrate(CalibrationSetup(PyramidConfig(binning=4, oversampling=1), 54), optics_cache)


def test_the_registered_mirror_is_the_calibrations(calibration):
    pupil = Pyramid(calibration.setup.pyramid).pupil
    plain = Mirror(calibration, pupil, None, 1000.0)
    same = Mirror(calibration, pupil, None, 1000.0, Misregistration())
    assert (plain.influence != same.influence).nnz == 0
    moved = Mirror(calibration, pupil, None, 1000.0, Misregistration(shift_x_pitch=0.5))
    c = np.random.default_rng(1).standard_normal(calibration.basis.M.shape[0])
    # the projections are the calibration's modes: a moved mirror's shape projects onto them
    # as the residual's stage computes it (a disturbance equal to the shape leaves no residual)
    shape = moved.shape(c)[0]
    _, y, modes = moved.shape_and_modes(c, shape)
    assert np.abs(modes).max() > 0.01
    np.testing.assert_allclose(moved.residual_modes(modes, c, y, 0.0), 0.0, atol=1e-9)


def test_the_moved_mirrors_coupling_is_the_identity_when_registered_and_cached(calibration, optics_cache, tmp_path):
    """R D' = I for the registered mirror (to the sparse influence functions' 1e-4 floor);
    shifted, its diagonal falls and it is no longer symmetric (complex eigenvalues); a second
    call reads the cached D' bit for bit."""
    R = calibration.reconstructor
    np.testing.assert_allclose(R @ moved_mirror_response(calibration, Misregistration()), np.eye(54), atol=2e-3)
    cache = ArrayCache(tmp_path)
    shifted = Misregistration(shift_x_pitch=1.0)
    D = moved_mirror_response(calibration, shifted, cache)
    np.testing.assert_array_equal(moved_mirror_response(calibration, shifted, cache), D)
    q = R @ D
    assert np.mean(np.diag(q)) < 0.95 and np.abs(np.linalg.eigvals(q).imag).max() > 0.1


def test_the_loop_loses_strehl_as_the_mirror_moves_and_the_description_keeps_it(optics_cache):
    """R11 flux on the 10x10 configuration (54 modes): registered 205 nm; 1 and 2 pitches
    238 and 524 nm (seed 1, 1 s, 0.6"); here the order, on 0.5 s."""
    obs = dataclasses.replace(observation_for_magnitude(17), magnitude_r=11.0)
    base = RunConfig(observation=obs, duration_s=0.5, oversampling=1, wfs_field_arcsec=0.0).with_values({"atmosphere.seeing_arcsec": 0.6})
    residual, verdicts = [], []
    for shift in (0.0, 1.0, 2.0):
        config = dataclasses.replace(base, misregistration=Misregistration(shift_x_pitch=shift))
        assert RunConfig.from_dict(config.to_dict()) == config  # the TOML form keeps it
        result = run(config.request(), optics_cache)
        assert result.diverged_at is None
        residual.append(result.metrics.residual_nm)
        verdicts.append(result.coupling)
    assert residual[0] < 0.95 * residual[1] and residual[1] < 0.8 * residual[2], residual
    # the eigenmodes of R D' (control.coupling): none when registered, all stable at 1 pitch
    # (margin 2.7), 8 of 54 unstable at 2 pitches (margin 0.39): the loop is lost, not diverged
    assert verdicts[0] is None and verdicts[1].stable and verdicts[1].margin > 1.5
    assert verdicts[2].unstable > 0 and verdicts[2].margin < 1
    assert "the loop is lost" in result.failure() and result.diverged_at is None
