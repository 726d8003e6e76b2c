"""The run description: lossless TOML, one place of validation, the one factory of requests."""

from __future__ import annotations

import json
import tomllib
from dataclasses import asdict
from pathlib import Path

import pytest

from soulctl import defaults, tables
from soulctl.defaults import SOUL_FIELD_OF_VIEW_ARCSEC
from soulctl.errors import InputError
from soulctl.observation import observation_for_magnitude
from soulctl.optics.asm import SIGN_SEED
from soulctl.optics.cache import cache_key
from soulctl.run_config import HEADER, RunConfig, read_run_config

EXPLICIT = """
[star]
magnitude_r = 9.7
[wfs]
binning = 1
frame_rate_hz = 1000.0
modulation_lambda_over_d = 3.0
[control]
modes = 500
tt_control = "int"
gains = [0.4, 0.4, 0.4]
forgetting = 1.0
[delay]
frames = 2
[atmosphere]
r0_m = 0.15
L0_m = 40.0
[[atmosphere.layer]]
altitude_m = 0.0
fraction = 1.0
wind_speed_m_s = 10.0
wind_direction_deg = 0.0
[vibrations]
enabled = false
[structure]
enabled = false
[detector]
noise = false
[run]
seed = 7
"""


def round_trip(c: RunConfig) -> RunConfig:
    return RunConfig.from_dict(tomllib.loads(c.to_toml()))


def test_defaults_round_trip_and_resolve():
    c = RunConfig()
    assert round_trip(c) == c
    r = c.resolved()
    assert round_trip(r) == r
    assert len(r.controller.gains) == 3 and all(type(g) is float for g in r.controller.gains)
    assert r.request().gains == c.request().gains  # the description's gains, the defaults' today


def test_explicit_run_round_trips_and_reaches_the_request():
    c = RunConfig.from_dict(tomllib.loads(EXPLICIT))
    assert round_trip(c) == c
    obs = c.observation
    assert (obs.binning, obs.modes, obs.frame_rate_hz, obs.tt_control) == (1, 500, 1000.0, "int")
    assert obs.delay_frames == pytest.approx(2.0)
    req = c.request()
    assert req.vibrations is None and req.structure is None and not req.noise and req.seed == 7
    atm = req.atmosphere()
    assert len(atm.layers) == 1 and atm.layers[0].wind_speed_m_s == 10.0 and req.L0_m == 40.0
    assert atm.r0_m == pytest.approx(0.15)  # r0 given, seeing derived, r0 recovered
    g = req.gains
    assert (g.tip_tilt, g.mid, g.high, g.forgetting) == (0.4, 0.4, 0.4, 1.0)


def test_per_mode_gains_round_trip_and_reach_the_loop():
    c = RunConfig.from_dict({"star": {"magnitude_r": 16.5}, "control": {"mode_gains": [0.3, 0.3] + [0.2] * 88, "forgetting": 1.0}})
    assert round_trip(c) == c
    g = c.request().gains
    assert g.per_mode(90)[:3].tolist() == [0.3, 0.3, 0.2] and g.forgetting == 1.0
    assert c.with_values({"control.gains": [0.1, 0.2, 0.3]}).controller.mode_gains == ()
    assert RunConfig.from_dict({"control": {"forgetting": 1.0}}).request().gains.forgetting == 1.0  # default gains, given forgetting


def test_vibration_scale_and_lines_round_trip():
    c = RunConfig.from_dict({"vibrations": {"scale": 2.0}})
    base = RunConfig().vibrations
    assert c.vibrations.lines[0].tip_mas == pytest.approx(2.0 * base.lines[0].tip_mas)
    assert round_trip(c) == c


def test_an_observation_file_is_a_run_description(tmp_path):
    obs = observation_for_magnitude(16.5)
    path = tmp_path / "obs.toml"
    path.write_text(obs.to_toml())
    c = read_run_config(path)
    assert c.observation == obs
    assert c.atmosphere.seeing_arcsec == defaults.SEEING_ARCSEC and c.duration_s == defaults.DURATION_S


def test_partial_observation_takes_the_table_row_key_by_key():
    c = RunConfig.from_dict({"star": {"magnitude_r": 16.5}, "wfs": {"frame_rate_hz": 1000.0}})
    table = observation_for_magnitude(16.5)
    assert c.observation.binning == table.binning and c.observation.modes == table.modes
    assert c.observation.frame_rate_hz == 1000.0 and c.observation.tt_filter_rate_hz != table.tt_filter_rate_hz


@pytest.mark.parametrize(
    "data, words",
    [
        ({"atmos": {}}, "unknown section [atmos]"),
        ({"atmosphere": {"seeing": 1.0}}, "unknown key 'seeing'"),
        ({"atmosphere": {"seeing_arcsec": 12.0}}, "atmosphere.seeing_arcsec"),
        ({"atmosphere": {"seeing_arcsec": "1"}}, "finite number"),
        ({"control": {"gains": [0.1, 0.2]}}, "3 values"),
        ({"control": {"mode_gains": [0.1, 0.2, 0.3]}}, "3 gains but 500 modes"),
        ({"control": {"gains": [0.1, 0.2, 0.3], "mode_gains": [0.1] * 500}}, "not both"),
        ({"control": {"forgetting": 1.5}}, "forgetting"),
        ({"delay": {"frames": 0.5}}, "1..10"),
        ({"delay": {"frames": 2, "t_asm_ms": 1.0}}, "total delay"),
        ({"run": {"band": "Q"}}, "run.band"),
        ({"run": {"seed": 1.5}}, "integer"),
        ({"structure": {"enabled": "yes"}}, "true or false"),
        ({"atmosphere": {"layer": [{"height": 0}]}}, "atmosphere.layer 1"),
        ({"mirror": {"influence": "spline"}}, "mirror.influence must be one of gaussian, thin-plate"),
        ({"mirror": {"coupling": 0.3}}, "unknown key 'coupling'"),
        ({"run": {"wfs_field_arcsec": 5.0}}, "run.wfs_field_arcsec must be in 0..4 arcsec"),
        ({"run": {"wfs_field_arcsec": "2.1"}}, "run.wfs_field_arcsec must be a finite number"),
    ],
)
def test_bad_descriptions_name_the_field(data, words):
    with pytest.raises(InputError) as e:
        RunConfig.from_dict(data)
    assert words in str(e.value)


def test_the_mirror_model_round_trips_and_reaches_the_calibration():
    """[mirror] influence chooses the influence functions, the thin plate by default; the
    Gaussian mirror keeps the basis cache key it had before the choice existed (so its cached
    bases stay valid), the thin plate has its own."""
    from soulctl.loop.run import calibration_setup

    gauss = RunConfig().with_values({"mirror.influence": "gaussian"})
    assert round_trip(gauss) == gauss and gauss.request().influence == "gaussian"
    assert RunConfig().influence == "thin-plate" and round_trip(RunConfig()).influence == "thin-plate"
    setups = [calibration_setup(c.request()) for c in (RunConfig(), gauss)]
    assert [s.basis.asm.influence for s in setups] == ["thin-plate", "gaussian"]
    assert setups[0].key() != setups[1].key()
    basis = setups[1].basis
    former = {k: v for k, v in asdict(basis.asm).items() if k != "influence"}
    assert basis.key() == cache_key("basis", {"asm": former, "L0_m": basis.L0_m, "pixels": basis.pixels, "sign_seed": SIGN_SEED})


def test_the_wfs_field_round_trips_and_reaches_the_calibration():
    """[run] wfs_field_arcsec: SOUL's 2.1", the default, gives the pyramid a field stop and a
    sensing pupil that holds it; 0 is the field the sampling gives, with the calibration's cache
    key it had before the choice existed.  Both are written, so that a stored description does
    not depend on the default."""
    from soulctl.loop.run import calibration_setup

    sampled = RunConfig().with_values({"run.wfs_field_arcsec": 0.0})
    assert RunConfig().wfs_field_arcsec == SOUL_FIELD_OF_VIEW_ARCSEC == 2.1 and RunConfig().request().wfs_field_arcsec == 2.1
    assert round_trip(sampled) == sampled and sampled.request().wfs_field_arcsec == 0.0
    assert sampled.to_dict()["run"]["wfs_field_arcsec"] == 0.0 and RunConfig().to_dict()["run"]["wfs_field_arcsec"] == 2.1
    plain, sensed = (calibration_setup(c.request()) for c in (sampled, RunConfig()))
    assert (plain.pyramid.sensing_oversampling, sensed.pyramid.sensing_oversampling) == (2, 3)
    assert plain.key() != sensed.key()
    former = {k: v for k, v in asdict(plain.pyramid).items() if k not in ("band_nm", "field_stop_lambda_over_d", "field_of_view_arcsec")}
    key = {"pyramid": former, "n_modes": plain.n_modes, "basis": plain.basis.key(), "push_nm": plain.push_nm}
    assert plain.key() == cache_key("calibration", key)


def test_a_stored_description_without_the_wfs_field_re_runs_the_sampled_field(tmp_path):
    """Telemetry and descriptions soulctl wrote before SOUL's field was the default hold no
    ``wfs_field_arcsec`` (0 was not written): they re-run the field they ran with, 0, while a
    description written by hand without the key takes the default."""
    import h5py

    text = RunConfig().with_values({"run.seed": 4}).to_toml()
    old = text.replace("wfs_field_arcsec = 2.1\n", "")
    assert old != text
    path = tmp_path / "old.h5"
    with h5py.File(path, "w") as f:
        f.attrs["run_description"] = old
    recorded = read_run_config(path)
    assert recorded.wfs_field_arcsec == 0.0 and recorded.seed == 4
    (tmp_path / "old.toml").write_text(old)
    assert old.startswith(HEADER) and read_run_config(tmp_path / "old.toml").wfs_field_arcsec == 0.0
    (tmp_path / "hand.toml").write_text(old.removeprefix(HEADER))
    assert read_run_config(tmp_path / "hand.toml").wfs_field_arcsec == 2.1


def test_with_values_overrides_dotted_fields():
    c = RunConfig().with_values({"atmosphere.seeing_arcsec": 0.6, "run.seed": 3})
    assert c.atmosphere.seeing_arcsec == 0.6 and c.seed == 3
    m = c.with_values({"star.magnitude_r": 16.5})
    assert m.observation == observation_for_magnitude(16.5) and m.atmosphere.seeing_arcsec == 0.6
    with pytest.raises(InputError, match="unknown run description field"):
        c.with_values({"atmosphere.sseing": 1.0})


def test_overrides_re_derive_what_they_make_stale():
    base = RunConfig()
    b = base.with_values({"wfs.binning": 4})
    assert b.observation.modes == next(r.modes for r in tables.magnitude_table() if r.binning == 4)
    r = base.with_values({"wfs.frame_rate_hz": 500.0})
    assert r.observation.tt_control == "int" and r.observation.tt_zeros == ()
    i = base.with_values({"wfs.frame_rate_hz": 1000.0})
    assert i.observation.tt_control == "iir" and i.observation.tt_filter_rate_hz == 1000.0
    v = base.with_values({"vibrations.enabled": False}).with_values({"vibrations.enabled": True})
    assert v.vibrations == base.vibrations
    kept = base.with_values({"star.magnitude_r": 13.0, "wfs.binning": 1})
    assert kept.observation.binning == 1 and kept.observation.magnitude_r == 13.0


def test_the_guide_shows_the_resolved_default_the_tool_prints(capsys):
    from soulctl.cli.app import main

    readme = (Path(__file__).parents[1] / "docs" / "guide.md").read_text()
    block = readme.split("<!-- print-config -->", 1)[1].split("```toml\n", 1)[1].split("```", 1)[0]
    assert main(["loop", "run", "--print-config"]) == 0
    assert capsys.readouterr().out == block


def test_ogtl_is_on_by_default_when_the_run_lets_it_act():
    """SOUL runs OGTL on sky (the paper): on by default once the loop can close and OGTL update
    twice (2.1 s at 1700 Hz), off below; an explicit value is kept; the stored description
    holds the decision."""
    base = RunConfig()  # R9.7, 1700 Hz
    assert base.auxiliary.ogtl is None and "ogtl" not in base.to_dict()["auxiliary"]
    assert base.resolved().auxiliary.ogtl is False  # 0.2 s
    assert base.with_values({"run.duration_s": 2.1}).resolved().auxiliary.ogtl is True
    assert base.with_values({"run.duration_s": 2.0}).resolved().auxiliary.ogtl is False
    assert base.with_values({"run.duration_s": 3.0, "auxiliary.ogtl": False}).resolved().auxiliary.ogtl is False
    stored = base.with_values({"run.duration_s": 3.0}).resolved().to_dict()
    assert stored["auxiliary"]["ogtl"] is True and RunConfig.from_dict(stored).auxiliary.ogtl is True
    faint = base.with_values({"star.magnitude_r": 16.5, "run.duration_s": 5.0})  # 250 Hz: 5.4 s needed
    assert faint.resolved().auxiliary.ogtl is False
    assert faint.with_values({"run.duration_s": 5.4}).resolved().auxiliary.live().ogtl


def test_the_sky_default_carries_luci1s_ncpa_compensated_where_ogtl_runs():
    """100 nm of NCPA (the paper's LUCI1) in every plain run; the reference-slope offsets come
    with OGTL (short runs: neither), unless the description says otherwise.  The description
    keeps the choice automatic, so that a stored run re-run without OGTL drops the offsets
    too (applied at k = 1 they lose the loop)."""
    assert RunConfig().ncpa.rms_nm == defaults.NCPA_RMS_NM == 100.0
    assert RunConfig(duration_s=0.2).request().ncpa.compensated is False
    long = RunConfig(duration_s=3.0).resolved()
    assert long.auxiliary.ogtl is True and long.ncpa.compensated is None and long.request().ncpa.compensated is True
    assert RunConfig(duration_s=3.0).with_values({"auxiliary.ogtl": False}).request().ncpa.compensated is False
    assert RunConfig(duration_s=0.2).with_values({"ncpa.compensated": True}).request().ncpa.compensated is True
    assert RunConfig(duration_s=0.2).request(ogtl=True).ncpa.compensated is True  # `optimize gains`' own OGTL
    stored = RunConfig.from_dict(tomllib.loads(long.to_toml()))
    assert stored.ncpa == long.ncpa and stored.request().ncpa == long.request().ncpa
    rerun = stored.with_values({"auxiliary.ogtl": False})
    assert rerun.request().ncpa.compensated is False
    assert RunConfig.from_dict({}).ncpa == RunConfig().ncpa  # a section left out is the default


def test_the_offsets_fraction_defaults_to_half_round_trips_and_reaches_the_request():
    """``ncpa.offset_fraction`` (``defaults.NCPA_OFFSET_FRACTION``, 0.5): stored with the run,
    refused outside 0..1 naming the field, and in the request (test_ncpa: what it does)."""
    assert RunConfig().ncpa.offset_fraction == defaults.NCPA_OFFSET_FRACTION == 0.5
    c = RunConfig(duration_s=3.0).with_values({"ncpa.offset_fraction": 0.8})
    assert round_trip(c).request().ncpa.offset_fraction == 0.8
    assert RunConfig.from_dict({"ncpa": {"rms_nm": 50.0}}).ncpa.offset_fraction == 0.5
    for bad in (-0.1, 1.5, "half"):
        with pytest.raises(InputError, match="ncpa.offset_fraction"):
            RunConfig().with_values({"ncpa.offset_fraction": bad})


def test_ideal_turns_ogtl_and_the_error_terms_off(capsys):
    from soulctl.cli.app import main

    assert main(["loop", "run", "--duration", "3", "--ideal", "--print-config", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["auxiliary"]["ogtl"] is False and d["ncpa"]["rms_nm"] == 0 and d["misregistration"]["shift_x_pitch"] == 0
    assert main(["loop", "run", "--duration", "3", "--print-config", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["auxiliary"]["ogtl"] is True
    assert main(["loop", "run", "--ideal", "--ncpa", "50", "--print-config"]) == 2
    assert "--ideal turns OGTL and the error terms off" in capsys.readouterr().err
