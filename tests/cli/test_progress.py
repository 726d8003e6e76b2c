"""The frames progress bar of `loop run` and `optimize gains`."""

from __future__ import annotations

from soulctl.cli.common import frames_progress


def test_hidden_bar_yields_no_callback():
    with frames_progress("closed loop", show=False) as tick:
        assert tick is None


def test_shown_bar_takes_both_callback_forms():
    # `run` reports frames done; `optimize` frames done and the total it now expects
    with frames_progress("closed loop", show=True, total=10) as tick:
        assert tick is not None
        tick(3)
        tick(5, 20)
