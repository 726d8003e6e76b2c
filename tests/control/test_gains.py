"""The gains module: the paper's groups, per-mode <-> per-state mapping, defaults, stability,
capping and the gain file, each against an independent statement of what it must give."""

import dataclasses

import numpy as np
import pytest

from soulctl.control.gains import (
    LoopGains,
    capped_gains,
    check_stability,
    default_gains,
    design_gains,
    gain_groups,
    gains_toml,
    group_summary,
    mode_filters,
    mode_gains,
    nominal_loop,
    read_gain_file,
    state_gains,
)
from soulctl.control.rtc import build_rtc
from soulctl.control.structure import StructuralResonance
from soulctl.control.transfer import max_stable_gain
from soulctl.errors import InputError
from soulctl.observation import observation_for_magnitude

OBS = observation_for_magnitude(9.7)  # the Tip/Tilt IIR at 1700 Hz


def test_groups_are_the_papers_three():
    assert [(n, s.start, s.stop) for n, s in gain_groups(500)] == [("tip-tilt", 0, 2), ("modes 3-120", 2, 120), ("modes 121-500", 120, 500)]
    assert [s.stop for _, s in gain_groups(54)] == [2, 54]
    assert [s.stop for _, s in gain_groups(1)] == [1]


def test_group_summary_of_a_vector():
    g = np.concatenate([[0.7, 0.5], np.linspace(0.2, 0.4, 118), np.full(380, 0.1)])
    rows = group_summary(g)
    assert [r["modes"] for r in rows] == ["1-2", "3-120", "121-500"]
    assert rows[0] == {"group": "tip-tilt", "modes": "1-2", "mean": 0.6, "min": 0.5, "max": 0.7}
    assert rows[1]["mean"] == pytest.approx(0.3) and rows[1]["min"] == pytest.approx(0.2) and rows[1]["max"] == pytest.approx(0.4)
    assert [r["modes"] for r in group_summary(np.ones(54))] == ["1-2", "3-54"]


def test_per_mode_and_back():
    g = LoopGains(0.6, 0.3, 0.2)
    v = g.per_mode(500)
    assert v[0] == v[1] == 0.6 and set(v[2:120]) == {0.3} and set(v[120:]) == {0.2}
    back = LoopGains.from_modes(v)
    assert (back.tip_tilt, back.mid, back.high) == pytest.approx((0.6, 0.3, 0.2))
    np.testing.assert_array_equal(back.per_mode(500), v)
    with pytest.raises(InputError, match="the gain file has 500 gains but 54 modes"):
        back.per_mode(54)


@pytest.mark.parametrize("bad", [-0.1, 10.5, float("nan"), float("inf")])
def test_gains_outside_the_range_are_refused_naming_it(bad):
    with pytest.raises(InputError, match=r"gain mid must be a number in 0\.\.10"):
        LoopGains(0.5, bad, 0.2)


def test_state_gains_put_each_modes_gain_on_all_its_states():
    """The Tip/Tilt IIR has several states, the leaky integrators one: Delta holds the mode's
    gain on each of them, and reading one per mode gives the vector back."""
    n_modes = 6
    gains = np.array([0.69, 0.6, 0.3, 0.25, 0.2, 0.1])
    filters = mode_filters(OBS, LoopGains.from_modes(gains), n_modes)
    mats = build_rtc(filters, np.eye(n_modes, 12), np.eye(8, n_modes), state_size=64)
    delta = state_gains(mats.blocks, mats.n_states, gains)
    for b in mats.blocks:
        assert set(delta[b.offset : b.offset + b.n_states]) == {gains[b.mode]}
    assert mats.blocks[0].n_states == filters[0].n_states > 1
    np.testing.assert_array_equal(mode_gains(mats.blocks, n_modes, delta), gains)
    np.testing.assert_array_equal(mats.Delta, delta)  # what the RTC is built with


def test_default_gains_pass_the_stability_check_and_a_too_high_gain_does_not():
    structure = StructuralResonance()
    g = default_gains(OBS, structure)
    check_stability(OBS, g, structure)
    g_max = max_stable_gain(nominal_loop(OBS, 0.1, False, structure))
    assert g.mid == pytest.approx(0.5 * g_max, abs=1e-3)
    with pytest.raises(InputError, match=rf"modes 3-120 gain .* \(maximum stable gain {g_max:.3f}\)"):
        check_stability(OBS, LoopGains(g.tip_tilt, 1.05 * g_max, g.high), structure)


def test_design_gains_keep_a_sampled_resonance_drop_one_above_nyquist_and_keep_given_gains():
    """The one rule runs, optimisations and checks start from: the 127 Hz resonance lowers an
    integrator's Tip/Tilt gain at 1700 Hz (0.17 against 0.26 without it), is left out at 250 Hz
    (where the resonance model itself refuses the rate), and explicit gains pass unchanged."""
    integrator = dataclasses.replace(OBS, tt_control="int", tt_zeros=(), tt_poles=())
    with_resonance = design_gains(integrator, StructuralResonance())
    assert with_resonance == default_gains(integrator, StructuralResonance())
    assert with_resonance.tip_tilt < 0.8 * default_gains(integrator, None).tip_tilt
    slow = observation_for_magnitude(16.5)
    assert slow.frame_rate_hz < 2 * StructuralResonance().frequency_hz
    with pytest.raises(InputError, match="needs a frame rate above"):
        default_gains(slow, StructuralResonance())
    assert design_gains(slow, StructuralResonance()) == default_gains(slow, None)
    given = LoopGains(0.1, 0.2, 0.3)
    assert design_gains(slow, StructuralResonance(), given) is given


def test_capping_uses_the_stable_gain_of_the_plant_with_optical_gain():
    """A leaky integrator with chi = 2 is stable up to half the nominal loop's g_max."""
    g_max = max_stable_gain(nominal_loop(OBS, 1.0, False, None))
    chi = np.array([1.0, 1.0, 2.0, 1.0])
    gains = np.array([0.5, 0.5, 0.9 * g_max, 0.2])
    capped = capped_gains(gains, OBS, None, chi, 0.99, fraction=0.5)
    assert capped[2] == pytest.approx(0.5 * g_max / 2, rel=2e-3)
    assert capped[3] == 0.2  # below its cap: unchanged


def test_gain_file_round_trip(tmp_path):
    g = np.round(np.random.default_rng(3).uniform(0, 1, 57), 5)
    path = tmp_path / "g.toml"
    path.write_text(gains_toml(g, "a test\nover two lines"))
    np.testing.assert_array_equal(read_gain_file(path), g)
    csv = tmp_path / "g.csv"
    csv.write_text("mode,gain\n3,0.3\n1,0.1\n2,0.2\n")
    np.testing.assert_array_equal(read_gain_file(csv), [0.1, 0.2, 0.3])
    csv.write_text("mode,gain\n3,0.3\n1,0.1\n")
    with pytest.raises(InputError, match=r"the modes must be 1\.\.2, each once"):
        read_gain_file(csv)
