"""The time-domain delay line against the plant's z^-d."""

import numpy as np
import pytest

from soulctl.control.transfer import Plant
from soulctl.errors import InputError
from soulctl.loop.delay_line import DelayLine


@pytest.mark.parametrize("d", [1.0, 2.0, 2.3, 3.57, 5.99])
def test_impulse_response_is_the_plants_numerator(d):
    line = DelayLine(1, d)
    response = []
    for k in range(10):
        response.append(line.applied()[0])
        line.push(np.array([1.0 if k == 0 else 0.0]))
    expected = np.zeros(10)
    num = Plant(d).numerator()
    expected[: len(num)] = num
    np.testing.assert_allclose(response, expected, atol=1e-15)


def test_a_delay_below_one_frame_is_refused():
    with pytest.raises(InputError, match="at least 1 frame"):
        DelayLine(3, 0.5)
