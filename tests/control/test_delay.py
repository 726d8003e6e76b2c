"""The loop delay model against the paper's figures, and the fractional-delay model against a
direct simulation of a held command seen by an integrating detector."""

import numpy as np
import pytest

from soulctl.control.delay import DelayModel, fractional_taps
from soulctl.errors import InputError


def test_soul_minimum_delay_is_the_papers_2_1_ms():
    assert DelayModel.from_table("soul").total_s(1700) * 1e3 == pytest.approx(2.1, abs=0.05)


def test_flao_delay_is_the_papers_3_1_ms_at_1000_hz():
    assert DelayModel.from_table("flao").total_s(1000) * 1e3 == pytest.approx(3.1, abs=0.05)


def test_delay_grows_with_frame_period_and_frames_shrink():
    m = DelayModel.from_table()
    rates = [100, 250, 500, 750, 1000, 1350, 1700]
    ms = [m.total_s(f) for f in rates]
    frames = [m.frames(f) for f in rates]
    assert all(a > b for a, b in zip(ms, ms[1:]))
    assert all(a < b for a, b in zip(frames, frames[1:]))
    assert frames[0] > 1.0  # never less than the one frame of exposure + hold


def test_fractional_taps():
    n, e = fractional_taps(3.57)
    assert n == 3 and e == pytest.approx(0.57)
    assert fractional_taps(2.0) == (2, 0.0)
    with pytest.raises(InputError):
        fractional_taps(-1)
    with pytest.raises(InputError):
        fractional_taps(float("inf"))
    with pytest.raises(InputError):
        DelayModel.from_table().total_s(0)


@pytest.mark.parametrize("latency_frames", [0.0, 0.3, 0.57, 1.25, 2.9])
def test_interpolation_is_the_sampled_response_of_held_commands(latency_frames):
    """A command c(k) computed at the end of frame k is applied after a latency and held; the
    detector integrates the mirror over each frame.  The measurement is then exactly
    (1-e) c(k-n) + e c(k-n-1) with d = 1 + latency, n = floor(d), e = d - n."""
    rng = np.random.default_rng(0)
    commands = rng.normal(size=40)
    sub = 1000  # time samples per frame
    t = (np.arange(60 * sub) + 0.5) / sub  # time in frames
    # mirror position: command k applies from t = k + 1 + latency (computed at the end of frame k)
    idx = np.floor(t - 1 - latency_frames).astype(int)
    mirror = np.where((idx >= 0) & (idx < len(commands)), commands[np.clip(idx, 0, len(commands) - 1)], 0.0)
    measured = mirror.reshape(60, sub).mean(axis=1)  # frame j integrates over [j, j+1)
    n, e = fractional_taps(1.0 + latency_frames)
    c = np.concatenate([np.zeros(10), commands, np.zeros(20)])  # c[k+10] = commands[k]
    model = np.array([(1 - e) * c[j - n + 10] + e * c[j - n - 1 + 10] for j in range(50)])
    np.testing.assert_allclose(measured[:50], model, atol=2e-3)
