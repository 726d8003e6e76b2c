"""`loop run`'s library side: default gains, the stability check, the request's limits."""

import dataclasses

import pytest

from soulctl.control.gains import LoopGains, check_stability, default_gains
from soulctl.control.structure import StructuralResonance, sampled_structure
from soulctl.errors import InputError
from soulctl.loop.run import RunRequest
from soulctl.observation import observation_for_magnitude


def test_default_gains_are_the_papers_iir_gain_and_stable_fractions():
    obs = observation_for_magnitude(9.7)
    g = default_gains(obs)
    assert g.tip_tilt == 0.69  # the paper's optimised 1700 Hz IIR gain
    check_stability(obs, g, StructuralResonance())
    obs_int = dataclasses.replace(obs, tt_control="int", tt_zeros=(), tt_poles=())
    assert default_gains(obs_int).tip_tilt == pytest.approx(0.5 * 0.34, abs=0.005)  # half of g_max with the resonance


def test_unstable_group_gain_names_the_maximum():
    obs = observation_for_magnitude(12.0)  # 738 Hz by the frame-rate rule
    with pytest.raises(InputError, match=r"modes 3-120 gain 3 is unstable at 738 Hz \(maximum stable gain 0.98"):
        check_stability(obs, LoopGains(0.3, 3.0, 0.2), StructuralResonance())


def test_the_resonance_is_left_out_below_twice_its_frequency():
    r = StructuralResonance()
    assert sampled_structure(r, 1700.0) is r and sampled_structure(r, 250.0) is None


def test_request_limits():
    obs = observation_for_magnitude(9.7)
    with pytest.raises(InputError, match="duration"):
        RunRequest(observation=obs, duration_s=0.0)
    with pytest.raises(InputError, match="unknown band"):
        RunRequest(observation=obs, band="L")
    with pytest.raises(InputError, match="too coarse for 500 modes: accepted up to 90"):
        RunRequest(observation=obs, oversampling=1, wfs_field_arcsec=0.0)
    r = RunRequest(observation=obs, duration_s=1.0)
    assert r.frames == 1700 and r.skip == 340


def test_a_run_longer_than_its_screens_says_the_turbulence_repeats(optics_cache, monkeypatch):
    """Screens grow with the run so that its turbulence does not repeat (1.3 s at 100 m/s: the
    fastest layer crosses 440 m); where the memory cap stops them (here lowered to 512^2 px),
    the run says its turbulence repeats."""
    from soulctl.loop.run import run
    from soulctl.optics import atmosphere
    from soulctl.run_config import RunConfig

    obs = dataclasses.replace(observation_for_magnitude(17), magnitude_r=11.0)
    base = RunConfig(observation=obs, oversampling=1, wfs_field_arcsec=0.0).with_values(
        {"atmosphere.wind_m_s": 100.0, "run.duration_s": 1.3}
    )
    grown = run(base.request(), optics_cache)
    assert not any("repeats" in n for n in grown.notes), grown.notes
    monkeypatch.setattr(atmosphere, "MAX_SCREEN_PIXELS", 512**2)
    capped = run(base.request(), optics_cache)
    assert any("the turbulence repeats after" in n for n in capped.notes), capped.notes


def test_the_thin_plate_mirror_reaches_the_loop(optics_cache):
    """`[mirror] influence = "thin-plate"` (the default) reaches the calibration and the loop's
    mirror, and a mis-registered thin-plate mirror moves with its own functions (thin-plate
    splines through the moved actuators)."""
    from soulctl.loop.run import calibration_for, closed_loop_for
    from soulctl.optics.registration import Misregistration
    from soulctl.run_config import RunConfig

    obs = dataclasses.replace(observation_for_magnitude(17), magnitude_r=11.0)
    config = RunConfig(observation=obs, oversampling=1, duration_s=0.05, wfs_field_arcsec=0.0).with_values(
        {"mirror.influence": "thin-plate"}
    )
    request = dataclasses.replace(config.request(), misregistration=Misregistration(shift_x_pitch=0.2))
    cal = calibration_for(request, optics_cache)
    assert cal.basis.geometry.influence == "thin-plate"
    loop = closed_loop_for(request, cal, default_gains(obs), None)
    g, pupil = cal.basis.geometry, loop.mirror.pupil
    moved = g.sparse_influence_functions(pupil, registration=request.misregistration)
    assert abs(loop.mirror.influence - moved).max() == 0.0
    assert abs(dataclasses.replace(g, influence="gaussian").sparse_influence_functions(pupil) - moved).max() > 0.1
    loop.run(request.frames)
