"""Observation set-up from the look-up table: frame-rate rule, Tip/Tilt controller, TOML."""

import math
import re

import pytest

from soulctl import tables
from soulctl.errors import InputError
from soulctl.observation import Observation, frame_rate, observation_for_magnitude, tt_filter_roots

BANDS = tables.magnitude_table()


def test_frame_rate_hits_the_table_at_each_rows_edges():
    for band in BANDS:
        assert frame_rate(band.r_min, band) == band.frame_rate_max_hz
        assert frame_rate(band.r_max, band) == band.frame_rate_min_hz


def test_frame_rate_falls_with_flux_inside_each_row():
    for band in BANDS[1:]:
        mags = [band.r_min + (band.r_max - band.r_min) * k / 20 for k in range(21)]
        rates = [frame_rate(m, band) for m in mags]
        assert all(a >= b for a, b in zip(rates, rates[1:])) and rates[0] > rates[-1]


def test_frame_rate_is_a_power_law_of_the_flux():
    """f ∝ F^p inside a row: equal flux ratios give equal frame-rate ratios."""
    band = BANDS[1]
    r1, r2, r3 = 10.8, 11.3, 11.8
    f1, f2, f3 = (frame_rate(r, band) for r in (r1, r2, r3))
    assert f1 / f2 == pytest.approx(f2 / f3, rel=0.01)


@pytest.mark.parametrize(
    "mag, paper_rate, paper_binning",
    [(10.9, 1212, 1), (11.9, 990, 1), (13.0, 980, 2)],
)
def test_rule_is_near_the_papers_operating_points(mag, paper_rate, paper_binning):
    """The paper's operating points are single observations, not a published rule; the rule
    stays within 25% of them (comparison in docs/physics.md)."""
    obs = observation_for_magnitude(mag)
    assert obs.binning == paper_binning
    assert obs.frame_rate_hz == pytest.approx(paper_rate, rel=0.25)


def test_tt_controller_choice():
    roots = tables.tt_iir_table()
    assert tt_filter_roots(1700, roots).frame_rate_hz == 1700
    assert tt_filter_roots(1361, roots).frame_rate_hz == 1350
    assert tt_filter_roots(1148, roots).frame_rate_hz == 1000
    assert tt_filter_roots(875, roots).frame_rate_hz == 1000  # tie: the higher rate
    assert tt_filter_roots(750, roots).frame_rate_hz == 750
    assert tt_filter_roots(749, roots) is None
    assert observation_for_magnitude(9.7).tt_control == "iir"
    assert observation_for_magnitude(17.0).tt_control == "int"


def test_bright_star_configuration():
    obs = observation_for_magnitude(9.7)
    assert (obs.binning, obs.subapertures, obs.modes, obs.frame_rate_hz) == (1, 40, 500, 1700)
    assert obs.delay_s * 1e3 == pytest.approx(2.1, abs=0.05)
    assert obs.delay_frames == pytest.approx(obs.delay_s * 1700)
    assert obs.tt_zeros == (-0.310, 0.690, 0.698, 0.705)


def test_toml_round_trip(tmp_path):
    for mag in (5.0, 11.2, 13.0, 15.5, 18.0):
        obs = observation_for_magnitude(mag)
        path = tmp_path / f"obs{mag}.toml"
        obs.write_toml(path)
        back = Observation.read_toml(path)
        assert back.to_dict() == obs.to_dict()
        assert math.isclose(back.delay_frames, obs.delay_frames)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(f"obs{m}.toml" for m in (5.0, 11.2, 13.0, 15.5, 18.0))
    assert all(p.stat().st_mode & 0o777 == 0o644 for p in tmp_path.iterdir())


def test_edited_toml_is_revalidated_and_derived_values_recomputed(tmp_path):
    path = tmp_path / "obs.toml"
    observation_for_magnitude(13.0).write_toml(path)
    text = path.read_text().replace("frame_rate_hz = 1148.0", "frame_rate_hz = 800.0")
    path.write_text(text.replace("delay_frames = 2.7315", "delay_frames = 99.0"))
    obs = Observation.read_toml(path)
    assert obs.frame_rate_hz == 800 and obs.delay_frames == pytest.approx(obs.delay_s * 800)
    path.write_text(text.replace("binning = 2", "binning = 5"))
    with pytest.raises(InputError, match="binning must be one of 1, 2, 3, 4, got 5"):
        Observation.read_toml(path)
    path.write_text("[star]\nmagnitude_r = 3\n")
    with pytest.raises(InputError, match="missing the key 'wfs'"):
        Observation.read_toml(path)
    path.write_text("not = [toml")
    with pytest.raises(InputError, match="not valid TOML"):
        Observation.read_toml(path)
    path.write_bytes(b"\xff\xfe\x00binary")
    with pytest.raises(InputError, match="not UTF-8 text"):
        Observation.read_toml(path)
    with pytest.raises(InputError, match="is a directory: soulctl reads regular files only"):
        Observation.read_toml(tmp_path)
    with pytest.raises(InputError, match="not found"):
        Observation.read_toml(tmp_path / "missing.toml")


ZEROS_1000 = "tt_zeros = [\n    0.337,\n    0.345,\n    0.345,\n    0.353,\n]"
PHOTOMETRY = "[photometry]\nzero_point_ph_s_per_subaperture = 264700000.0\n"


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda t: t.replace(ZEROS_1000, 'tt_zeros = "1234"'), "control.tt_zeros must be a list of numbers"),
        (lambda t: t.replace("binning = 2", "binning = true"), "wfs.binning must be an integer"),
        (lambda t: t.replace("modes = 250", "modes = 250.7"), "control.modes must be an integer"),
        (lambda t: t.replace("= 264700000.0", "= -1.0"), "zero point must be a positive"),
        (lambda t: "photometry = [1]\n" + t.replace(PHOTOMETRY, ""), "[photometry] must be a table"),
    ],
)
def test_wrong_types_in_a_configuration_file_are_refused(edit, message, tmp_path):
    path = tmp_path / "obs.toml"
    observation_for_magnitude(13.0).write_toml(path)
    text = path.read_text()
    edited = edit(text)
    assert edited != text
    path.write_text(edited)
    with pytest.raises(InputError, match=re.escape(message)):
        Observation.read_toml(path)


def test_non_finite_or_unstable_poles_are_refused():
    obs = observation_for_magnitude(9.7).to_dict()
    obs["control"]["tt_poles"] = [0.1, 0.2, float("nan"), 1.0]
    with pytest.raises(InputError, match="tt_poles must be finite and in -1..1"):
        Observation.from_dict(obs)
