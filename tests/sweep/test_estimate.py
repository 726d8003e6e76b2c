"""The estimated cost of a sweep: frames per case as the loop runs them, a measured cost for
every binning and oversampling a case can have, and a 90 000-case grid estimated at once."""

import time

import pytest

from soulctl.loop.optimize import OGTL_MAX_SETTLING_PERIODS, OGTL_SETTLING_PERIODS, OPTIMISER_OGTL
from soulctl.sweep.case import observation_for, optimisation_period_s
from soulctl.sweep.estimate import CALIBRATION_S, CASE_FIXED_S, FRAME_MS, case_cost, estimate
from soulctl.sweep.grid import parse_grid


def test_every_binning_and_oversampling_has_a_measured_cost():
    expected = {(b, o) for b in (1, 2, 3, 4) for o in (1, 2, 3, 4)} - {(1, 1), (2, 1)}  # o = 1 only up to 90 modes
    assert set(FRAME_MS) == set(CASE_FIXED_S) == set(CALIBRATION_S) == expected
    assert all(FRAME_MS[b, 4] > FRAME_MS[b, 2] for b in (1, 2, 3, 4))


def test_frames_of_a_case():
    case = {"magnitude": 16.6, "binning": 4, "oversampling": 1, "duration": 0.5}
    rate = observation_for(case).frame_rate_hz
    n, seconds, setup = case_cost(case)
    assert n == round(0.5 * rate) and seconds == pytest.approx(CASE_FIXED_S[4, 1] + n * FRAME_MS[4, 1] / 1e3)
    mgm, _, _ = case_cost({**case, "gain_method": "mgm"})
    trial, _, _ = case_cost({**case, "gain_method": "trial"})
    assert mgm > 3 * n and trial > 2 * n
    assert case_cost({"magnitude": 12.0, "oversampling": 1}) == (0, 0.0, None)  # 500 modes at o = 1: fails at once


def test_the_paired_evaluation_is_counted_with_its_twelve_ogtl_updates():
    """Each of the two evaluation loops settles for OGTL_MAX_SETTLING_PERIODS updates when the
    optimiser runs OGTL (``optimize.evaluation_settle_s``), not for the run's least settling."""
    assert OPTIMISER_OGTL
    case = {"magnitude": 16.6, "binning": 4, "oversampling": 1, "duration": 0.5, "gain_method": "mgm"}
    obs = observation_for(case)
    rate = obs.frame_rate_hz
    n, period = round(0.5 * rate), round(optimisation_period_s(0.5, obs) * rate)
    frames, _, _ = case_cost(case)
    assert frames >= OGTL_SETTLING_PERIODS * period + 3 * n + 2 * (OGTL_MAX_SETTLING_PERIODS * period + n)


def test_a_large_grid_is_estimated_at_once():
    cases = parse_grid(
        {"magnitude": [16.6, 17.0, 17.5], "seeing": [0.6, 0.8, 1.0, 1.2, 1.4], "seed": list(range(1, 6001)), "duration": 0.5}
    )
    t0 = time.perf_counter()
    e = estimate(cases, 2)
    assert time.perf_counter() - t0 < 5
    assert e.cases == 90_000 and e.calibrations == 1 and e.wall_seconds == pytest.approx(e.cpu_seconds / 2 / 0.82)
    assert e.text().startswith("estimate: 90000 cases, ") and "on 2 workers" in e.text()
    assert estimate(cases[:3], None).as_json()["wall_seconds"] is None
