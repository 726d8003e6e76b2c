"""The modal temporal PSD model: Noll's radial orders, the cut-off, the normalisation and the
slopes of Conan et al. (1995)."""

import numpy as np
import pytest
from scipy.integrate import quad

from soulctl.disturbance.modal_psd import cutoff_hz, modal_psd, radial_order


def test_radial_orders_are_nolls():
    # Noll j = 2..11: n = 1, 1, 2, 2, 2, 3, 3, 3, 3, 4
    assert radial_order(np.arange(1, 11)).tolist() == [1, 1, 2, 2, 2, 3, 3, 3, 3, 4]
    assert radial_order([54, 90])[0] == 9  # j = 55 closes order 9: 55 = 10 * 11 / 2


def test_psd_integrates_to_the_variance_with_its_slopes():
    fc = cutoff_hz([30], 8.0, 8.222)[0]
    assert fc == pytest.approx(0.3 * 8 * 8.0 / 8.222)
    total, _ = quad(lambda f: modal_psd([f], [100.0], [fc])[0, 0], 0, np.inf, limit=200)
    assert total == pytest.approx(100.0, rel=1e-6)
    low = modal_psd([0.01 * fc, 0.1 * fc], [1.0], [fc])[0]
    assert low[1] / low[0] == pytest.approx(1.0, abs=1e-5)  # flat below the cut-off
    high = modal_psd([10 * fc, 100 * fc], [1.0], [fc])[0]
    assert np.log(high[1] / high[0]) / np.log(10) == pytest.approx(-17 / 3, rel=1e-3)  # f^(-17/3) above
