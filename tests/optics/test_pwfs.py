"""The modulated pyramid WFS: geometry, linearity, linear range and sensitivity against the
geometric-optics theory of the modulated pyramid (Verinaud 2004; Fauvarque et al. 2016)."""

import numpy as np
import pytest

from soulctl.errors import InputError
from soulctl.optics.detector import Detector
from soulctl.optics.pwfs import Pyramid, PyramidConfig, modulation_points
from soulctl.optics.sensor import WavefrontSensor

LAMBDA_OVER_D_RAD = 750e-9 / 8.222


def sensor(**kwargs) -> WavefrontSensor:
    config = PyramidConfig(**{"oversampling": 1, **kwargs})
    return WavefrontSensor(Pyramid(config), Detector(read_noise_e=0, excess_noise=False), photons_per_frame=1.0)


def tip_map(wfs: WavefrontSensor, angle_lambda_over_d: float, axis: int = 0) -> np.ndarray:
    """OPD (nm) of a tilt of the beam by ``angle`` lambda/D along x (axis 0) or y (axis 1)."""
    p = wfs.pupil
    n = p.n_pixels
    c = (np.arange(n) + 0.5 - n / 2) * p.pixel_scale_m
    x, y = np.meshgrid(c, c)
    ramp = (x, y)[axis] * angle_lambda_over_d * LAMBDA_OVER_D_RAD * 1e9
    return (ramp * p.mask).astype(np.float32)


def mean_slopes(wfs: WavefrontSensor, opd: np.ndarray) -> tuple[float, float]:
    s = wfs.slopes(opd)
    n = wfs.n_subapertures
    return float(s[:n].mean()), float(s[n:].mean())


@pytest.mark.parametrize("binning, across", [(1, 40), (2, 20), (3, 13), (4, 10)])
def test_subapertures_across_the_pupil_follow_the_binning(binning, across):
    p = Pyramid(PyramidConfig(binning=binning, oversampling=2))
    valid = p.valid_map
    assert valid.sum(axis=1).max() == across and valid.sum(axis=0).max() == across
    # an annulus of sub-apertures: about pi/4 (1 - 0.111^2) of the square, with the edges
    assert valid.sum() == pytest.approx(np.pi / 4 * (1 - 0.111**2) * across**2, rel=0.12)


def test_modulation_points_rule():
    assert modulation_points(0) == 1
    assert modulation_points(3) == 24  # SPECULA's 2 round(4 r) at 3 lambda/D
    assert all(modulation_points(r) % 4 == 0 and 2 * np.pi * r / modulation_points(r) <= np.pi / 4 + 1e-12 for r in (0.5, 1.3, 2, 5.7))


def test_unaberrated_beam_lights_the_four_pupil_images_equally():
    p = Pyramid(PyramidConfig(binning=1, oversampling=1))
    I = p.reference_intensity
    h = I.shape[0] // 2
    quadrants = [I[:h, :h].sum(), I[:h, h:].sum(), I[h:, :h].sum(), I[h:, h:].sum()]
    assert I.sum() == pytest.approx(1.0, rel=1e-5)
    np.testing.assert_allclose(quadrants, 0.25, rtol=0.01)


def test_tip_response_is_linear_signed_and_matches_the_modulated_pyramid_gain():
    """Small tilt theta << r: s = (2/pi) arcsin(theta / r) ~ 2 theta / (pi r) (geometric optics)."""
    wfs = sensor(binning=2, modulation_lambda_over_d=3.0)
    angles = np.array([0.05, 0.1, 0.2])
    sx = np.array([mean_slopes(wfs, tip_map(wfs, a))[0] for a in angles])
    sy_of_tilt = np.array([mean_slopes(wfs, tip_map(wfs, a, axis=1))[1] for a in angles])
    np.testing.assert_allclose(sx / angles, sx[0] / angles[0], rtol=0.01)  # linear
    np.testing.assert_allclose(sy_of_tilt, sx, rtol=0.02)  # same along y
    assert mean_slopes(wfs, tip_map(wfs, 0.1))[1] == pytest.approx(0, abs=1e-4)  # no cross-talk
    assert sx[0] > 0
    assert sx[0] / angles[0] == pytest.approx(2 / (np.pi * 3.0), rel=0.2)


def test_high_order_mode_response_is_linear():
    wfs = sensor(binning=2)
    p = wfs.pupil
    n = p.n_pixels
    c = (np.arange(n) + 0.5) / n
    x, y = np.meshgrid(c, c)
    mode = (np.cos(2 * np.pi * 9 * x) * np.cos(2 * np.pi * 6 * y) * p.mask).astype(np.float32)  # ~10 cycles/pupil
    s1, s2, s4 = (wfs.slopes(a * mode) for a in (2.0, 4.0, 8.0))
    assert np.linalg.norm(s1) > 1e-3
    np.testing.assert_allclose(s2, 2 * s1, atol=0.02 * np.abs(s2).max())
    np.testing.assert_allclose(s4, 4 * s1, atol=0.05 * np.abs(s4).max())


def linear_range(modulation: float) -> float:
    """The tilt (lambda/D) at which the Tip response falls 10 % below its small-signal line."""
    wfs = sensor(binning=4, modulation_lambda_over_d=modulation)
    gain = mean_slopes(wfs, tip_map(wfs, 0.05))[0] / 0.05
    for angle in np.arange(0.25, 12.0, 0.25):
        if mean_slopes(wfs, tip_map(wfs, angle))[0] < 0.9 * gain * angle:
            return float(angle)
    return np.inf


def test_linear_range_widens_with_the_modulation_radius():
    ranges = [linear_range(r) for r in (1.0, 3.0, 5.0)]
    assert ranges[0] < ranges[1] < ranges[2]
    # geometric theory: s = (2/pi) arcsin(theta/r) up to theta = r, then s = 1; it falls 10 %
    # below the small-signal line 2 theta / (pi r) at theta = (pi / 1.8) r = 1.745 r
    assert ranges[1] == pytest.approx(1.745 * 3.0, rel=0.2)


def test_sensitivity_falls_as_the_modulation_grows():
    gains = []
    for r in (2.0, 4.0, 8.0):
        wfs = sensor(binning=4, modulation_lambda_over_d=r)
        gains.append(mean_slopes(wfs, tip_map(wfs, 0.05))[0] / 0.05)
    assert gains[0] > gains[1] > gains[2]
    # Tip gain ~ 1/r: halving with each doubling of r
    assert gains[0] / gains[1] == pytest.approx(2.0, rel=0.15)
    assert gains[1] / gains[2] == pytest.approx(2.0, rel=0.15)


def _sensor_of(config: PyramidConfig) -> WavefrontSensor:
    return WavefrontSensor(Pyramid(config), Detector(read_noise_e=0, excess_noise=False), photons_per_frame=1.0)


def _high_order_mode(wfs: WavefrontSensor) -> np.ndarray:
    p = wfs.pupil
    c = (np.arange(p.n_pixels) + 0.5) / p.n_pixels
    x, y = np.meshgrid(c, c)
    return (np.cos(2 * np.pi * 9 * x) * np.cos(2 * np.pi * 6 * y) * p.mask).astype(np.float32)  # ~11 cycles/pupil


def test_chromatic_response_tilt_by_angle_high_orders_by_phase():
    """At the same modulation angle: a small tilt's signal depends on the angle only (geometric
    optics, s = 2 theta / (pi r), both in radians), at any wavelength; a mode of spatial
    frequency beyond the modulation is sensed by its phase, so per nm of OPD as 1/lambda; and
    under a 150 nm residual the red end keeps more of its gain (the same OPD is less phase)."""
    base = PyramidConfig(binning=2, oversampling=1, modulation_lambda_over_d=3.0)
    sensors = {w: _sensor_of(base.monochromatic(w)) for w in (650.0, 900.0)}
    tilt = {w: mean_slopes(wfs, tip_map(wfs, 0.1))[0] for w, wfs in sensors.items()}
    assert tilt[650.0] == pytest.approx(tilt[900.0], rel=0.02)
    mode = _high_order_mode(sensors[650.0])
    linear = {w: wfs.slopes(5 * mode) - wfs.slopes(-5 * mode) for w, wfs in sensors.items()}
    assert np.linalg.norm(linear[650.0]) / np.linalg.norm(linear[900.0]) == pytest.approx(900 / 650, rel=0.06)
    n = mode.shape[0]
    x, y = np.meshgrid(np.arange(n) / n, np.arange(n) / n)
    rng = np.random.default_rng(2)
    residual = np.zeros((n, n))
    for fx, fy in rng.integers(1, 15, (60, 2)):  # a rough f^-11/3 spectrum up to 14 cycles
        residual += np.cos(2 * np.pi * (fx * x + fy * y) + rng.uniform(0, 2 * np.pi)) / np.hypot(fx, fy) ** (11 / 6)
    mask = sensors[650.0].pupil.mask > 0
    residual = (150 * residual / residual[mask].std() * mask).astype(np.float32)
    kept = {}
    for w, wfs in sensors.items():
        d = wfs.slopes(residual + 5 * mode) - wfs.slopes(residual - 5 * mode)
        kept[w] = float(d @ linear[w] / (linear[w] @ linear[w]))
    assert 0.5 < kept[650.0] < kept[900.0] < 1.0  # 0.745 and 0.853


def test_a_band_is_the_mean_of_its_wavelengths():
    """A polychromatic beam of equal photon weights: the frame is the mean of its wavelengths'
    normalised frames, each at the band's modulation angle; one wavelength at 750 nm is the
    monochromatic default, bit for bit."""
    base = PyramidConfig(binning=4, oversampling=1)
    opd = np.random.default_rng(3).normal(0, 80, (40, 40)).astype(np.float32)
    band = Pyramid(PyramidConfig(binning=4, oversampling=1, band_nm=(650.0, 900.0)))
    parts = [Pyramid(base.monochromatic(w)).intensity(opd) for w in (650.0, 900.0)]
    np.testing.assert_allclose(band.intensity(opd), (parts[0] + parts[1]) / 2, rtol=1e-5, atol=1e-9)
    same = PyramidConfig(binning=4, oversampling=1, band_nm=[900, 650.0])  # any order, any sequence: one form
    assert same == band.config and hash(same) == hash(band.config)
    assert base.monochromatic(900.0).modulation_lambda_over_d == pytest.approx(3.0 * 750 / 900)
    one = Pyramid(PyramidConfig(binning=4, oversampling=1, band_nm=(750.0,)))
    np.testing.assert_array_equal(one.intensity(opd), Pyramid(base).intensity(opd))


@pytest.mark.parametrize(
    "kwargs",
    [
        {"binning": 5},
        {"binning": 0},
        {"modulation_lambda_over_d": -1.0},
        {"oversampling": 7},
        {"wavelength_m": 0.0},
        {"band_nm": (200.0, 750.0)},
        {"band_nm": (float("nan"),)},
        {"band_nm": (750.0,) * 10},
        {"band_nm": (320.0,), "modulation_lambda_over_d": 10.0},  # 23 lambda/D at 320 nm
        {"band_nm": ("750",)},
    ],
)
def test_non_physical_configurations_are_input_errors(kwargs):
    with pytest.raises(InputError) as e:
        PyramidConfig(**kwargs)
    assert isinstance(e.value, ValueError)
    if "band_nm" in kwargs:
        assert "WFS band" in str(e.value)


def test_wrong_opd_shape_is_an_input_error():
    p = Pyramid(PyramidConfig(binning=4, oversampling=1))
    with pytest.raises(InputError, match="40x40"):
        p.intensity(np.zeros((41, 41)))


def test_threads_share_the_modulation_points_without_changing_the_frame():
    """The modulation points shared between threads give the one-thread frame to the last bit
    (float32 sums depend on their order, and the order once followed the thread count: a
    closed loop then ran differently on machines with other cores), and the same frame every
    time; the binning equals the plain sum over detector pixels."""
    config = PyramidConfig(binning=2, oversampling=1)
    n = config.pupil.n_pixels
    opd = np.random.default_rng(4).standard_normal((2, n, n)).astype(np.float32) * 150
    one, two = Pyramid(config, workers=1), Pyramid(config, workers=2)
    frames = two.intensity(opd)
    for workers in (1, 3, 5, 8, 24):
        np.testing.assert_array_equal(Pyramid(config, workers=workers).intensity(opd), frames, err_msg=f"{workers} threads")
    np.testing.assert_array_equal(one.intensity(opd[1]), frames[1])  # one map as in a batch
    assert np.array_equal(frames, two.intensity(opd))
    # the unbinned intensity binned by hand
    unbinned = Pyramid(PyramidConfig(binning=1, oversampling=1), workers=2).intensity(opd[0])
    plain = unbinned.reshape(config.frame_shape[0], 2, config.frame_shape[1], 2).sum(axis=(1, 3))
    np.testing.assert_allclose(frames[0], plain, rtol=1e-4, atol=1e-6 * plain.max())
    with pytest.raises(InputError):
        Pyramid(config, workers=0)


def test_a_band_shares_one_thread_pool_and_travels_to_workers():
    """A band's wavelengths run one after the other on one thread pool (not one pool each), and
    a pickled band (a sweep's worker) gives the same frame."""
    import pickle

    band = Pyramid(PyramidConfig(binning=4, oversampling=1, band_nm=(650.0, 900.0)), workers=2)
    opd = np.random.default_rng(5).normal(0, 100, (40, 40)).astype(np.float32)
    frame = band.intensity(opd)
    assert band._pool is not None and all(p._pool is band._pool for p in band._parts)
    copy = pickle.loads(pickle.dumps(band))
    np.testing.assert_array_equal(copy.intensity(opd), frame)
    assert copy._pool is not None and all(p._pool is copy._pool for p in copy._parts)


def test_a_field_stop_removes_the_light_beyond_it_and_nothing_within():
    """A field stop on the pyramid (moving with it under the modulation): an unaberrated beam,
    whose light lies within a few lambda/D, keeps it all (the stop only rings the pupil images'
    edges); a tilt that puts the PSF beyond the stop leaves the detector dark; the stop scales
    with the wavelength as the modulation does."""
    plain = Pyramid(PyramidConfig(binning=4, oversampling=2))
    stopped = Pyramid(PyramidConfig(binning=4, oversampling=2, field_stop_lambda_over_d=20.0))
    # frames are normalised to the unaberrated beam's flux; beyond 20 lambda/D lie only the Airy wings (~1/(pi^2 r))
    assert 0.98 < plain._norm / stopped._norm < 1.0
    p = plain.pupil
    c = (np.arange(p.n_pixels) + 0.5 - p.n_pixels / 2) * p.pixel_scale_m
    x, _ = np.meshgrid(c, c)
    for angle, lit in ((10.0, True), (30.0, False)):  # the PSF at 10 and 30 lambda/D from the vertex
        opd = (x * angle * LAMBDA_OVER_D_RAD * 1e9 * p.mask).astype(np.float32)
        kept = stopped.intensity(opd).sum() / plain.intensity(opd).sum()
        assert (kept > 0.9) if lit else (kept < 0.05), (angle, kept)
    assert PyramidConfig(field_stop_lambda_over_d=30.0).monochromatic(900.0).field_stop_lambda_over_d == pytest.approx(25.0)
    with pytest.raises(InputError, match="field stop"):
        PyramidConfig(oversampling=2, field_stop_lambda_over_d=56.0)  # beyond the +-40 lambda/D of an 80-pixel pupil
    with pytest.raises(InputError, match="field stop"):
        PyramidConfig(field_stop_lambda_over_d=2.0)  # inside the modulation
    with pytest.raises(InputError, match="WFS band: at 600 nm"):
        PyramidConfig(oversampling=3, field_stop_lambda_over_d=56.0, band_nm=(600.0, 900.0))  # 70 lambda/D at 600 nm


def test_a_field_of_view_reads_the_sampled_pupil_through_a_field_that_holds_it():
    """``field_of_view_arcsec``: SOUL's 2.1" is a stop of radius 55.8 lambda/D at 750 nm on 8.222 m,
    beyond the +-40 lambda/D an 80-pixel pupil's focal plane holds; the pyramid reads the same
    80-pixel OPD interpolated on 120 pixels (+-60 lambda/D), onto the same detector."""
    wide = PyramidConfig(binning=4, oversampling=2, field_of_view_arcsec=2.1)
    assert wide.stop_lambda_over_d == pytest.approx(1.05 / 206264.806 / LAMBDA_OVER_D_RAD)
    assert (wide.sensing_oversampling, wide.field_lambda_over_d, wide.pupil.n_pixels) == (3, 60.0, 80)
    assert wide.frame_shape == PyramidConfig(binning=4, oversampling=2).frame_shape
    assert PyramidConfig(oversampling=4, field_of_view_arcsec=2.1).sensing_oversampling == 4  # already wide enough
    both = {"field_of_view_arcsec": 2.1, "field_stop_lambda_over_d": 30.0}
    bad_fields = ({"field_of_view_arcsec": 4.5}, {"field_of_view_arcsec": -1.0}, both)
    for bad in bad_fields:
        with pytest.raises(InputError, match="WFS field of view must be 0..4 arcsec"):
            PyramidConfig(oversampling=2, **bad)


def test_the_wide_field_reads_a_small_wavefront_as_the_sampled_pupil_does():
    """In the linear regime the field beyond 40 lambda/D holds no light: both pyramids give the
    same slopes (the interpolation of a smooth OPD changes nothing) within 2 %."""
    detector = Detector(read_noise_e=0, excess_noise=False)
    plain = WavefrontSensor(Pyramid(PyramidConfig(binning=4, oversampling=2)), detector, 1.0)
    wide = WavefrontSensor(Pyramid(PyramidConfig(binning=4, oversampling=2, field_of_view_arcsec=2.1)), detector, 1.0)
    p = plain.pupil
    x, y = (np.asarray(c) / p.diameter_m for c in np.meshgrid(*(2 * [(np.arange(p.n_pixels) + 0.5 - p.n_pixels / 2) * p.pixel_scale_m])))
    opd = (20 * np.sin(2 * np.pi * 3 * x) + 15 * np.cos(2 * np.pi * 2 * y) + 10 * x) * p.mask
    a, b = plain.slopes(opd.astype(np.float32)), wide.slopes(opd.astype(np.float32))
    assert np.corrcoef(a, b)[0, 1] > 0.99
    assert np.linalg.norm(b) / np.linalg.norm(a) == pytest.approx(1.0, abs=0.02)


@pytest.mark.parametrize("angle, sampled_sign, wide_lit", [(30.0, 1, True), (50.0, -1, True), (60.0, -1, False)])
def test_a_steep_tilt_lands_where_the_field_puts_it(angle, sampled_sign, wide_lit):
    """Geometric optics: a beam tilted by theta lambda/D puts its PSF at theta, on the faces of
    that side, and the pyramid's x signal saturates at +1.  The sampled pupil's focal plane is
    periodic with +-40 lambda/D: at 50 it puts the PSF at -30, on the opposite faces (the sign
    reversed), at 60 at -20 (the same).  The wide field reads 50 with the right sign and its
    55.8 lambda/D stop takes the beam at 60 away (the detector dark), as SOUL's field stop
    does.  Its own focal plane is periodic with +-60 lambda/D: a tilt beyond 2 x 60 - 55.8 =
    64.2 lambda/D (1.2") comes back inside the stop (docs/physics.md, the pyramid's field)."""
    detector = Detector(read_noise_e=0, excess_noise=False)
    plain = WavefrontSensor(Pyramid(PyramidConfig(binning=4, oversampling=2)), detector, 1.0)
    wide = WavefrontSensor(Pyramid(PyramidConfig(binning=4, oversampling=2, field_of_view_arcsec=2.1)), detector, 1.0)
    opd = tip_map(plain, angle)
    assert np.sign(mean_slopes(plain, opd)[0]) == sampled_sign and abs(mean_slopes(plain, opd)[0]) > 0.5
    flux = wide.pyramid.intensity(opd).sum()
    if wide_lit:
        assert flux > 0.9 and mean_slopes(wide, opd)[0] > 0.5
    else:
        assert flux < 0.1 and plain.pyramid.intensity(opd).sum() > 0.9  # the modulation circle (3 lambda/D) grazes the stop
