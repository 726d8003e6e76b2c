"""The simulated closed loop against the loop analysis: the rejection of a 13 Hz vibration
measured in the time domain equals |S(13 Hz)| of soulctl.control.transfer (two
representations, one truth), and turbulence is corrected."""

import dataclasses

import numpy as np
import pytest
from scipy.signal import welch

from soulctl.control.filters import Filter
from soulctl.control.gains import LoopGains
from soulctl.control.structure import StructuralResonance
from soulctl.control.transfer import Loop, Plant
from soulctl.disturbance.vibrations import VibrationLine, VibrationSpectrum
from soulctl.loop.simulation import ClosedLoop as _ClosedLoop
from soulctl.loop.simulation import LoopDiverged
from soulctl.observation import observation_for_magnitude
from soulctl.optics.atmosphere import AtmosphereConfig
from soulctl.optics.calibration import CalibrationSetup, calibrate
from soulctl.optics.pwfs import PyramidConfig
from soulctl.telemetry.figures import pseudo_open_loop
from soulctl.telemetry.recorder import MemorySink


def ClosedLoop(*args, **kwargs):  # noqa: N802 - the loop, with every frame kept for the test
    return _ClosedLoop(*args, sink=MemorySink(), **kwargs)


LINE_13HZ = VibrationSpectrum((VibrationLine(13.0, 0.003, tip_mas=5.0, tilt_mas=3.0),))


@pytest.fixture(scope="module")
def small_calibration(optics_cache):
    return calibrate(CalibrationSetup(PyramidConfig(binning=4, oversampling=1), 54), optics_cache)


def rejection(loop: ClosedLoop, frames: int, skip: int) -> np.ndarray:
    tm = loop.run(frames).arrays()
    return tm["residual_modes"][skip:, :2].std(axis=0) / tm["disturbance_modes"][skip:, :2].std(axis=0)


def test_integrator_rejection_of_a_13_hz_line_equals_the_analysis(small_calibration):
    obs = dataclasses.replace(observation_for_magnitude(9.7), frame_rate_hz=1000.0, tt_control="int", tt_zeros=(), tt_poles=())
    loop = ClosedLoop(obs, small_calibration, None, LoopGains(0.4, 0.3, 0.3), vibrations=LINE_13HZ, noise=False)
    expected = abs(1 / (1 + Loop(Filter.integrator(0.4), Plant(obs.delay_frames), 1000.0).open_loop(np.array([13.0]))))[0]
    np.testing.assert_allclose(rejection(loop, 1000, 200), expected, rtol=0.03)


def test_iir_rejection_of_a_13_hz_line_equals_the_analysis(small_calibration):
    """The paper's 1700 Hz Tip/Tilt IIR at g = 0.69: |S(13 Hz)| = 0.11."""
    obs = observation_for_magnitude(9.7)
    assert obs.tt_control == "iir" and obs.frame_rate_hz == 1700
    loop = ClosedLoop(obs, small_calibration, None, LoopGains(0.69, 0.3, 0.3), vibrations=LINE_13HZ, noise=False)
    iir = Filter.iir(obs.tt_zeros, obs.tt_poles, 0.69)
    expected = abs(1 / (1 + Loop(iir, Plant(obs.delay_frames), 1700.0).open_loop(np.array([13.0]))))[0]
    assert expected == pytest.approx(0.11, abs=0.015)
    np.testing.assert_allclose(rejection(loop, 1400, 400), expected, rtol=0.05)


def test_a_run_split_in_pieces_is_the_same_run(small_calibration):
    """Turbulence, vibrations and noise do not depend on how the frames are split between run
    calls (the optimiser's phases split one loop in three)."""
    obs = dataclasses.replace(observation_for_magnitude(9.7), frame_rate_hz=1000.0)
    args = (obs, small_calibration, AtmosphereConfig.lbt_default(1.0), LoopGains(0.3, 0.3, 0.3))
    whole = ClosedLoop(*args, vibrations=VibrationSpectrum.lbt_default(), seed=4).run(300).arrays()
    split = ClosedLoop(*args, vibrations=VibrationSpectrum.lbt_default(), seed=4)
    for n in (40, 1, 259):
        split.run(n)
    np.testing.assert_array_equal(split.telemetry.arrays()["disturbance_modes"], whole["disturbance_modes"])
    np.testing.assert_array_equal(split.telemetry.arrays()["residual_modes"], whole["residual_modes"])


def test_pseudo_open_loop_with_the_structure_recovers_the_disturbance(small_calibration):
    """Tip/Tilt's plant is z^-d (1 + G): the pseudo-open loop rebuilt with the structure's G
    matches the true disturbance; without it, it misses the structure's response to the
    commands near 127 Hz (driven here by a 120 Hz line)."""
    obs = dataclasses.replace(observation_for_magnitude(9.7), frame_rate_hz=1000.0, tt_control="int", tt_zeros=(), tt_poles=())
    structure = StructuralResonance()
    near_resonance = VibrationSpectrum((VibrationLine(13.0, 0.003, 5.0, 3.0), VibrationLine(120.0, 0.01, 2.0, 2.0)))
    loop = ClosedLoop(obs, small_calibration, None, LoopGains(0.3, 0.3, 0.3), vibrations=near_resonance, noise=False, structure=structure)
    tm = loop.run(800).arrays()
    ba = structure.coefficients(1000.0)
    truth = tm["disturbance_modes"][100:, :2]
    with_structure = pseudo_open_loop(tm["measured_modes"], tm["command_modes"], obs.delay_frames, ba)[100:, :2]
    without = pseudo_open_loop(tm["measured_modes"], tm["command_modes"], obs.delay_frames)[100:, :2]
    error = np.sqrt(np.mean((with_structure - truth) ** 2))
    assert error < 0.03 * truth.std()
    assert np.sqrt(np.mean((without - truth) ** 2)) > 3 * error


def test_turbulence_is_corrected(small_calibration):
    """10x10 sub-apertures and 54 modes at 1" seeing leave a large residual (fitting error
    ~275 nm, and the pyramid's optical gains ~0.2 at that residual slow the loop down), but
    the controlled modes are held well below their open-loop level."""
    obs = dataclasses.replace(observation_for_magnitude(9.7), frame_rate_hz=1000.0)
    loop = ClosedLoop(obs, small_calibration, AtmosphereConfig.lbt_default(1.0), LoopGains(0.5, 0.4, 0.4), noise=False)
    tm = loop.run(300).arrays()
    res, dist = tm["residual_modes"][100:], tm["disturbance_modes"][100:]
    assert np.sqrt((res**2).sum(axis=1).mean()) < 0.45 * np.sqrt((dist**2).sum(axis=1).mean())
    # the residual keeps the uncontrolled modes (fitting error) but far less than open loop
    open_loop_rms = np.sqrt(
        np.mean([np.mean((loop.disturbance_opd(k) - loop.disturbance_opd(k).mean()) ** 2) for k in range(100, 300, 20)])
    )
    assert tm["residual_rms_nm"][100:].mean() < 0.6 * open_loop_rms


def test_disturbance_modes_are_the_projection_of_the_disturbance(small_calibration):
    """The telemetry's disturbance modes come from the residual's by linearity (mirror,
    structure and piston terms): they equal the direct projection of the disturbance OPD."""
    obs = observation_for_magnitude(9.7)
    loop = ClosedLoop(
        obs,
        small_calibration,
        AtmosphereConfig.lbt_default(1.0),
        LoopGains(0.5, 0.4, 0.4),
        vibrations=VibrationSpectrum.lbt_default(),
        noise=True,
        seed=3,
    )
    tm = loop.run(60).arrays()
    direct = np.array([loop.project(loop.disturbance_opd(k)) for k in range(60)])
    assert np.abs(direct[-1]).max() > 10  # a real disturbance, with the structure excited
    np.testing.assert_allclose(tm["disturbance_modes"], direct, atol=1e-6 * np.abs(direct).max())


def test_same_seed_same_loop(small_calibration):
    obs = observation_for_magnitude(12.0)
    runs = []
    for seed in (5, 5, 6):
        loop = ClosedLoop(
            obs,
            small_calibration,
            AtmosphereConfig.lbt_default(1.0),
            LoopGains(0.5, 0.4, 0.4),
            vibrations=VibrationSpectrum.lbt_default(),
            noise=True,
            seed=seed,
        )
        runs.append(loop.run(20).arrays()["measured_modes"])
    assert np.array_equal(runs[0], runs[1]) and not np.array_equal(runs[0], runs[2])


def test_integrator_at_high_gain_excites_the_127_hz_structure_and_the_iir_does_not(small_calibration):
    """No scripted threshold: the structural resonance in the loop (control.structure) makes
    the 1700 Hz integrator at g = 0.3 ring near 127 Hz, the paper's IIR at g = 0.69 not, and
    the integrator at g = 0.45 (above its maximum stable gain 0.34) diverge."""
    obs = observation_for_magnitude(9.7)
    obs_int = dataclasses.replace(obs, tt_control="int", tt_zeros=(), tt_poles=())

    def band_power(o, g):
        loop = ClosedLoop(o, small_calibration, None, LoopGains(g, 0.3, 0.3), vibrations=VibrationSpectrum.lbt_default(), seed=2)
        tt = loop.run(1200).arrays()["residual_modes"][300:, 0] * loop.mas_per_nm_tt
        f, p = welch(tt, fs=1700.0, nperseg=256)
        return p[(f > 110) & (f < 145)].sum() * (f[1] - f[0])

    assert band_power(obs_int, 0.3) > 5 * band_power(obs, 0.69)
    loop = ClosedLoop(obs_int, small_calibration, None, LoopGains(0.45, 0.3, 0.3), vibrations=VibrationSpectrum.lbt_default(), seed=2)
    with pytest.raises(LoopDiverged, match="loop diverged at frame") as e:
        loop.run(1200)
    assert len(loop.telemetry.residual_rms_nm) == e.value.frame + 1  # the telemetry so far is kept
