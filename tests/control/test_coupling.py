"""The coupled loop's stability (mis-registration) against the scalar loop's own margins: the
gain margin from the closed-loop poles (``max_stable_gain``) and the phase margin from the
Nyquist curve (``analyze``), and the closed-loop poles from np.roots."""

import json
import math

import numpy as np
import pytest
from scipy.linalg import block_diag

from soulctl.control.coupling import coupling_stability, pole_radii
from soulctl.control.filters import Filter
from soulctl.control.structure import StructuralResonance
from soulctl.control.transfer import Loop, Plant, analyze, max_stable_gain

RATE = 1000.0
IIR_1700 = Filter.iir((-0.31, 0.69, 0.698, 0.705), (0.042, 0.102, 0.954, 1.0), 1.0)  # the paper's 1700 Hz Tip/Tilt IIR shape


def unit(d=2.0, forgetting=1.0):
    return Loop(Filter.leaky(forgetting, 1.0) if forgetting < 1 else Filter.integrator(1.0), Plant(d), RATE)


def rotations(phi_deg: float, n_blocks: int) -> np.ndarray:
    c, s = math.cos(math.radians(phi_deg)), math.sin(math.radians(phi_deg))
    return block_diag(*[np.array([[c, -s], [s, c]])] * n_blocks)


@pytest.mark.parametrize(
    "loop",
    [
        Loop(Filter.leaky(0.99, 1.0), Plant(2.6), RATE),
        Loop(
            Filter.iir((-0.31, 0.69, 0.698, 0.705), (0.042, 0.102, 0.954, 1.0), 1.0),
            Plant.with_structure(3.567, StructuralResonance(), 1700.0),
            1700.0,
        ),
    ],
    ids=["leaky integrator", "Tip/Tilt IIR with the 127 Hz structure"],
)
def test_pole_radii_are_the_closed_loop_poles_of_the_loop_at_that_gain(loop):
    """For real mu the scalar loop is ``loop`` at gain mu: its own characteristic polynomial's
    roots; for complex mu, np.roots of a q + mu b p."""
    rng = np.random.default_rng(3)
    real = rng.uniform(0.05, 1.5, 10)
    expected = [np.max(np.abs(loop.with_gain(m).closed_loop_poles())) for m in real]
    np.testing.assert_allclose(pole_radii(loop, real), expected, rtol=1e-8)
    mu = rng.normal(0.4, 0.3, 10) + 1j * rng.normal(0, 0.3, 10)
    b, a = loop.controller.coefficients()
    ap, bp = np.convolve(a, loop.plant.denominator()), np.convolve(b, loop.plant.numerator())
    n = max(ap.size, bp.size)
    ap, bp = np.pad(ap, (0, n - ap.size)), np.pad(bp, (0, n - bp.size))
    np.testing.assert_allclose(pole_radii(loop, mu), [np.max(np.abs(np.roots(ap + m * bp))) for m in mu], rtol=1e-8)


def test_a_plant_without_delay_can_put_a_pole_at_infinity():
    loop = Loop(Filter.integrator(1.0), Plant(0.0), RATE)  # 1 + mu = 0 at mu = -1
    assert math.isinf(pole_radii(loop, np.array([-1.0]))[0])
    verdict = coupling_stability(-np.eye(2), np.ones(2), loop, loop).to_dict()
    assert verdict["largest_pole"] == "inf" and verdict["unstable"] == 2 and json.dumps(verdict, allow_nan=False)


@pytest.mark.parametrize("d, g", [(1.0, 0.5), (2.0, 0.3), (2.73, 0.2)])
def test_without_coupling_the_margin_is_the_scalar_loops_gain_margin(d, g):
    """Q = I: every eigenmode is the scalar loop, lost exactly past its maximum stable gain."""
    loop = unit(d)
    g_max = max_stable_gain(loop.with_gain(g))
    verdict = coupling_stability(np.eye(6), np.full(6, g), loop, loop)
    assert verdict.stable and verdict.eigenmodes == 6 and verdict.largest_phase_deg == pytest.approx(0, abs=1e-9)
    assert verdict.margin == pytest.approx(g_max / g, rel=1e-6)
    assert coupling_stability(np.eye(6), np.full(6, 1.01 * g_max), loop, loop).unstable == 6


@pytest.mark.parametrize("d, g", [(2.0, 0.3), (3.5, 0.15)])
def test_a_rotation_of_the_modes_loses_the_loop_at_its_phase_margin(d, g):
    """Q made of 2x2 rotations by phi has eigenvalues exp(+-i phi): the loop g L e^{i phi} meets -1
    when phi reaches the phase margin of g L (e^{-i phi} too: over negative frequencies the loop
    with a complex gain is the conjugate's, so both of each pair are lost together)."""
    loop = unit(d)
    pm = analyze(loop.with_gain(g)).phase_margin_deg
    assert 20 < pm < 90
    gains = np.full(6, g)
    below = coupling_stability(rotations(pm - 1.0, 3), gains, loop, loop)
    above = coupling_stability(rotations(pm + 1.0, 3), gains, loop, loop)
    assert below.stable and below.margin > 1 and below.largest_phase_deg == pytest.approx(pm - 1.0)
    assert above.unstable == 6 and above.margin < 1 and above.largest_pole > 1


def test_tip_tilt_is_judged_with_its_own_loop():
    """A Tip/Tilt gain the other modes' loop could not take, stable with Tip/Tilt's own (one
    frame less delay): the 2x2 block goes to ``tip_tilt_unit``."""
    slow, fast = unit(3.0), unit(1.0)
    g = np.array([1.2, 1.2, 0.2, 0.2])
    assert coupling_stability(np.eye(4), g, fast, slow).stable
    assert coupling_stability(np.eye(4), g, slow, slow).unstable == 2
    assert math.isfinite(coupling_stability(np.eye(4), g, fast, slow).to_dict()["margin"])


def test_the_margin_is_found_far_above_and_is_zero_when_no_gain_helps():
    """A loop with a delay always has a finite margin, however small its gains (the search
    reaches 1e4); an eigenvalue with a negative real part drives an integrator the wrong way
    at every gain: margin 0, and the message says no factor helps."""
    loop = unit(1.4)
    g_max = max_stable_gain(loop.with_gain(0.1))
    tiny = coupling_stability(np.eye(2), np.full(2, 1e-3), loop, loop)
    assert tiny.margin == pytest.approx(g_max / 1e-3, rel=1e-6) and tiny.to_dict()["margin"] == tiny.margin
    wrong = coupling_stability(np.diag([1.0, 1.0, -0.5, 1.0]), np.full(4, 0.2), loop, loop)
    assert wrong.unstable == 1 and wrong.margin == 0.0 and "no common factor on the gains stabilises them" in wrong.unstable_text()


def test_a_mode_the_coupling_hides_from_its_integrator_is_judged():
    """A singular Q (a mode the moved mirror no longer makes) with a non-zero gain: its
    integrator sees no signal and keeps its pole at z = 1, a random walk, not a stable mode;
    with a leaky integrator it decays (pole 0.99)."""
    q = np.eye(4)
    q[3, 3] = 0.0
    assert coupling_stability(q, np.full(4, 0.3), unit(2.0), unit(2.0)).unstable == 1
    assert coupling_stability(q, np.full(4, 0.3), unit(2.0), unit(2.0, 0.99)).stable


def test_modes_at_gain_zero_are_not_in_the_loop():
    """A gain of 0 feeds nothing back: its integrator's pole at z = 1 is not a lost mode (the
    Tip/Tilt IIR has one), and with every gain 0 there is nothing to judge."""
    loop = unit(2.0)  # a pure integrator: pole at z = 1 at gain 0
    verdict = coupling_stability(rotations(30.0, 2), np.array([0.0, 0.0, 0.3, 0.3]), loop, loop)
    assert verdict.stable and verdict.eigenmodes == 2
    nothing = coupling_stability(np.eye(4), np.zeros(4), loop, loop)
    assert nothing.stable and nothing.eigenmodes == 0 and nothing.to_dict()["margin"] == "inf"


def test_a_lost_loop_counts_the_modes_its_gains_lose_when_registered():
    """`registration_verdict` (the call of `loop run` and `rtc check`): a 120-degree rotation of
    two modes loses the loop at a third of the maximum stable gain; gains above the maximum on
    three other modes (run with --allow-unstable) are unstable with the mirror registered too,
    and the verdict says so instead of blaming the mis-registration alone."""
    from soulctl.control.coupling import registration_verdict
    from soulctl.control.gains import unit_loops
    from soulctl.observation import observation_for_magnitude

    obs = observation_for_magnitude(16.5)
    filters, _ = unit_loops(obs, None, 0.99, obs.modes)
    g_max = max_stable_gain(Loop(filters[-1], Plant(obs.delay_frames), obs.frame_rate_hz))
    q = np.eye(obs.modes)
    q[10:12, 10:12] = rotations(120.0, 1)
    gains = np.full(obs.modes, g_max / 3)
    lost = registration_verdict(obs, None, 0.99, q, gains, obs.delay_frames)
    assert lost.unstable == 2 and lost.registered_unstable == 0 and "own doing" not in lost.unstable_text()
    gains[40:43] = 1.5 * g_max
    both = registration_verdict(obs, None, 0.99, q, gains, obs.delay_frames)
    assert both.unstable == 5 and both.registered_unstable == 3 and "the gains alone leave 3 modes unstable" in both.unstable_text()
    alone = registration_verdict(obs, None, 0.99, np.eye(obs.modes), gains, obs.delay_frames)  # registered: the gains' doing
    assert alone.unstable == alone.registered_unstable == 3
    assert json.loads(json.dumps(both.to_dict()))["registered_unstable"] == 3
