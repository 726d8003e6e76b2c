"""Records of another AO system (``foreign_records``: AOT files written with aotpy alone, a
quad-cell-like Tip/Tilt loop of known delay, chi and controller): identification from the two
axes, MGM with the record's own controller against a brute-force scan, the structural
resonance only where the record's corrector is LBT's, and the rate tolerance."""

import json

import aotpy
import numpy as np
import pytest
from cli_run import run
from foreign_records import LOW_PASS, RATE, modal_loop, tip_tilt_loop, write_aot
from scipy.signal import lfilter

from soulctl.identify.identify import identify
from soulctl.identify.plant import read_plant
from soulctl.offline.mgm import PlantInputs, offline_mgm
from soulctl.offline.recorded import checked_rate
from soulctl.telemetry.formats import open_telemetry

KECK_LIKE = (np.array([1.0]), np.array([1.0, -0.6, -0.32, -0.08]))  # an integrator times 1 / (1 + 0.4 z^-1 + 0.08 z^-2)


@pytest.fixture(scope="module")
def tip_tilt(tmp_path_factory):
    """60 s of a Tip/Tilt loop, an integrator with a low-pass at g = 0.6, d = 2.5, for chi 1 and 0.7."""
    root = tmp_path_factory.mktemp("foreign")
    out = {}
    for chi in (1.0, 0.7):
        m, c = tip_tilt_loop(60000, 0.6, chi=chi, seed=4)
        out[chi] = write_aot(root / f"tt_{chi}.fits", m, c, 0.6)
    return out


@pytest.mark.parametrize("chi", [1.0, 0.7])
def test_identify_finds_delay_and_chi_from_the_two_axes(tip_tilt, chi):
    """Within 0.1 frame and 10 % (today's main: exit 1, 'the rejection fit needs modes beyond
    Tip/Tilt'); the record states no delay, so the whole 0-6 frame span is searched."""
    ident = identify(tip_tilt[chi])
    assert ident.plant.delay.value == pytest.approx(2.5, abs=0.1)
    assert ident.plant.optical_gains[0].chi == pytest.approx(chi, rel=0.1)
    assert ident.plant.delay.sigma < 0.1 and ident.plant.optical_gains[0].sigma < 0.1 * chi
    assert ident.plant.optical_gains[0].first_mode == 1 and len(ident.plant.optical_gains) == 1


def test_identify_a_tip_tilt_record_in_every_format(tip_tilt, tmp_path, capsys):
    """The CLI on the record as AOT, soulctl HDF5 and an LBT folder: exit 0, the figures it
    cannot estimate null with the reason; a one-mode record too."""
    for target in (tip_tilt[1.0], tmp_path / "tt.h5", tmp_path / "Data_20261207_101010"):
        if target != tip_tilt[1.0]:
            assert run(["telemetry", "convert", tip_tilt[1.0], target], capsys)[0] == 0
        status, out, err = run(["telemetry", "identify", target, "--json"], capsys)
        assert status == 0, (target, err)
        d = json.loads(out)
        assert d["turbulence"] is None and "Tip/Tilt" in d["not_estimated"]["turbulence"]
        assert d["delay_frames"]["value"] == pytest.approx(2.5, abs=0.15), target
        assert [x["frequency_hz"]["value"] for x in d["vibration_lines"]] == pytest.approx([20.0], abs=0.1)
        with open_telemetry(target, required=()) as tm:  # the record's system, whatever its format: not LBT's
            assert (tm.attribute("sensor"), tm.attribute("corrector"), tm.attribute("telescope_diameter_m")) == (
                "quad-cell",
                "tip-tilt-mirror",
                10.0,
            )
        assert "structural resonance: none (the record's corrector: tip-tilt-mirror)" in d["notes"]
    m, c = modal_loop(20000, [0.5], [1.0], [1.0, -1.0], seed=2)
    one = write_aot(tmp_path / "one.fits", m, c, 0.5, [1.0], [1.0, -1.0])
    status, out, err = run(["telemetry", "identify", one, "--json"], capsys)
    d = json.loads(out)
    assert status == 0 and d["delay_frames"]["value"] == pytest.approx(2.5, abs=0.15), err
    assert "one mode" in d["not_estimated"]["vibration_lines"] and d["tip_tilt_noise_mas"] is None


def _brute_force_optimum(pol: np.ndarray, num, den, delay: float, chi: float, gains: np.ndarray) -> float:
    """The gain of least measured-residual variance, each gain's loop run in the time domain:
    residual = S(z) pol with S = a / (a + g chi b z^-n ((1 - e) + e z^-1))."""
    n, e = int(delay), delay - int(delay)
    b = np.convolve(num, np.r_[np.zeros(n), 1 - e, e])
    variances = []
    for g in gains:
        a = np.zeros(max(len(den), len(b)))
        a[: len(den)] += den
        a[: len(b)] += g * chi * b
        r = lfilter(den, a, pol, axis=0)[2000:]
        variances.append(np.mean(r**2))
    return float(gains[int(np.argmin(variances))])


def test_mgm_optimises_the_recorded_controller(tmp_path, capsys):
    """A loop whose controller is not an integrator (Keck's STRAP filter): MGM's optimum is the
    brute-force scan's within 5 %; read as an integrator (no denominator) it is not."""
    num, den = KECK_LIKE
    m, c = tip_tilt_loop(40000, 0.1, num, den, seed=5, noise=1.0)
    path = write_aot(tmp_path / "keck_like.fits", m, c, 0.1, num, den, delay=2.5)
    status, out, err = run(["optimize", "gains", "--telemetry", path, "--json"], capsys)
    result = json.loads(out)
    assert status == 0 and result["notes"] == ["structural resonance: none (the record's corrector: tip-tilt-mirror)"], err
    assert result["chi"] == [1.0, 1.0]
    n, e = 2, 0.5
    pol = m.copy()  # m + the mirror's commands, z^-2.5 of c
    pol[n:] += (1 - e) * c[:-n]
    pol[n + 1 :] += e * c[: -n - 1]
    scan = np.linspace(0.02, 1.25, 124)  # up to 0.96 of the loop's maximum stable gain, 1.302
    for axis in range(2):
        truth = _brute_force_optimum(pol[:, axis], num, den, 2.5, 1.0, scan)
        assert result["optimum"][axis] == pytest.approx(truth, rel=0.05), (axis, result["optimum"], truth)
    system = aotpy.AOSystem.read_from_file(str(path))
    system.loops[0].time_filter_den = None  # the same record stating its numerator alone
    bare = tmp_path / "bare.fits"
    system.write_to_file(str(bare))
    assumed = offline_mgm(bare, plant=PlantInputs(delay_frames=2.5))
    assert abs(assumed.optimum[0] / result["optimum"][0] - 1) > 0.1
    with open_telemetry(bare, required=()) as tm:
        assert any("integrators (1 - z^-1) taken" in note.text for note in tm.notes)


def test_the_resonance_only_for_lbts_adaptive_secondary(tip_tilt, tmp_path, capsys):
    """A tip-tilt mirror's record models no 127 Hz resonance; a deformable mirror of a
    telescope named LBT does; --resonance lbt|none overrides either."""
    rec = identify(tip_tilt[1.0]).record
    assert rec.structure_ba is None
    assert identify(tip_tilt[1.0], structure="lbt").record.structure_ba is not None
    system = aotpy.AOSystem.read_from_file(str(tip_tilt[1.0]))
    system.main_telescope.uid = "LBT"
    loop = system.loops[0]
    loop.commanded_corrector = aotpy.DeformableMirror("ASM", telescope=system.main_telescope, n_valid_actuators=672)
    system.wavefront_correctors = [loop.commanded_corrector]
    lbt = tmp_path / "lbt.fits"
    system.write_to_file(str(lbt))
    assert identify(lbt).record.structure_ba is not None and identify(lbt, structure="none").record.structure_ba is None
    status, out, err = run(["optimize", "gains", "--telemetry", lbt, "--delay-frames", "2.5", "--resonance", "none"], capsys)
    assert status == 0 and "--resonance none" in out, err


def test_a_measured_rate_agrees_with_a_nominal_one_within_the_tolerance():
    """1000.07 Hz (time stamps) is a 1000 Hz configuration's rate, used and said; 1010 Hz is not."""
    rate, note = checked_rate(1000.07, 1000.0, "x.h5")
    assert rate == 1000.07 and "1000.07" in note
    assert checked_rate(1000.0, 1000.0, "x.h5") == (1000.0, None)
    with pytest.raises(Exception, match="within 0.001"):
        checked_rate(1010.0, 1000.0, "x.h5")


def test_offline_mgm_of_a_quad_cell_needs_no_configuration(tip_tilt, tmp_path, capsys):
    """chi 1 for a quad cell, printed; --chi-table without --config/--mag; the table shows the
    optimum, MGM's gain and why they differ; a record without a delay asks for one."""
    status, _, err = run(["optimize", "gains", "--telemetry", tip_tilt[1.0]], capsys)
    assert status == 2 and "lacks delay_frames" in err and "give --delay-frames" in err
    status, out, err = run(["optimize", "gains", "--telemetry", tip_tilt[1.0], "--delay-frames", "2.5"], capsys)
    assert status == 0 and "quad-cell, not a pyramid" in out and "recorded → optimum → MGM" in out, err
    table = tmp_path / "og.csv"
    table.write_text("mode,optical_gain\n1,0.5\n2,0.5\n")
    status, out, err = run(
        ["optimize", "gains", "--telemetry", tip_tilt[1.0], "--delay-frames", "2.5", "--chi-table", table, "--json"], capsys
    )
    d = json.loads(out)
    assert status == 0 and d["chi"] == [0.5, 0.5] and len(d["reasons"]) == 2 and set(d["reasons"]) <= set(d["reason_legend"]), err


def test_psd_of_a_record_without_a_delay_and_its_noise_floor(tip_tilt, capsys):
    """--delay-frames gives the pseudo-open loop; the floor is the white noise put in (1 nm per
    frame: 2 / rate nm^2/Hz one-sided, chi 1)."""
    status, _, err = run(["telemetry", "psd", tip_tilt[1.0], "--pseudo-open-loop"], capsys)
    assert status == 2 and "give --delay-frames" in err
    status, out, err = run(["telemetry", "psd", tip_tilt[1.0], "--pseudo-open-loop", "--delay-frames", "2.5", "--json"], capsys)
    d = json.loads(out)
    assert status == 0 and err == ""
    assert np.mean(d["noise_floor_nm2_per_hz"]["pseudo_open_loop"]) == pytest.approx(2 / RATE, rel=0.1)
    j = d["tt_jitter"]["pseudo_open_loop"]
    assert j["all_floor_removed"] < j["all"] and j["all_noise_floor"] ** 2 + j["all_floor_removed"] ** 2 == pytest.approx(j["all"] ** 2)


def test_psd_of_a_short_record_warns_on_stderr(tmp_path, capsys):
    m, c = tip_tilt_loop(100, 0.5, *LOW_PASS, seed=1)
    path = write_aot(tmp_path / "short.fits", m, c, 0.5)
    status, out, err = run(["telemetry", "psd", path, "--json"], capsys)
    d = json.loads(out)
    assert status == 0 and err.count("soulctl: warning: ") == 2 and "resolution" in err
    assert d["tt_jitter_above_3hz_mas"]["measured_modes"] is None and len(d["warnings"]) == 2


def test_the_plant_file_keeps_a_recorded_controllers_complex_poles(tmp_path, capsys):
    """identify --out writes the record's Tip/Tilt filter; its complex poles were written as
    their real parts (a third-order real filter instead of Keck's), now as [re, im] pairs."""
    num, den = KECK_LIKE
    m, c = tip_tilt_loop(20000, 0.1, num, den, seed=6)
    path = write_aot(tmp_path / "keck_like.fits", m, c, 0.1, num, den)
    assert run(["telemetry", "identify", path, "--out", tmp_path / "plant.toml"], capsys)[0] == 0
    h = read_plant(tmp_path / "plant.toml").tip_tilt_filter
    b, a = h.coefficients()
    np.testing.assert_allclose(a, den, atol=1e-9)
    assert b == pytest.approx([0.1])


def test_rtc_check_takes_a_plant_whose_rate_was_measured(tmp_path, capsys):
    """A plant identified from a record whose rate came from time stamps (x 1.0001) checks a
    configuration at the nominal rate (exit 2 on today's main: rates compared within 1e-6);
    1 % off is refused naming both."""
    from soulctl.observation import observation_for_magnitude

    obs = observation_for_magnitude(16.5)
    gains = tmp_path / "gains.toml"
    gains.write_text("gains = [" + ", ".join(["0.1"] * obs.modes) + "]\n")
    for factor, expected in ((1.0001, 0), (1.01, 2)):
        plant = tmp_path / f"plant_{factor}.toml"
        plant.write_text(f'source = "test"\nrate_hz = {obs.frame_rate_hz * factor!r}\n\n[delay]\nframes = {obs.delay_frames!r}\n')
        status, out, err = run(["rtc", "check", gains, "--mag", "16.5", "--plant", plant, "--json"], capsys)
        assert status == expected, err
        if expected == 2:
            assert "the plant's rate" in err and "within 0.001" in err and err.count("\n") == 1
