"""One rule for a measured or derived number in a table or caption (``cli.output.figure_text``):
three significant digits, not six (the identified seeing printed 0.928629", the recorded delay
2.73348)."""

from __future__ import annotations

import math

import pytest

from soulctl.cli.output import figure_text
from soulctl.cli.telemetry import _recorded


@pytest.mark.parametrize(
    "value, text",
    [
        (0.928629, "0.929"),
        (2.73348, "2.73"),
        (7.56824, "7.57"),
        (8.0, "8"),
        (0.5, "0.5"),
        (12.345, "12.3"),
        (99.96, "100"),
        (1148.3, "1148"),
        (0.0012345, "0.00123"),
        (1.2e-5, "1.20e-05"),
        (-3.14159, "-3.14"),
        (0.0, "0"),
        (math.nan, "n/a"),
    ],
)
def test_three_significant_digits(value, text):
    assert figure_text(value) == text


def test_a_recorded_delay_reads_to_its_meaningful_digits():
    assert _recorded(2.73348) == "recorded 2.73"
