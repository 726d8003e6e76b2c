"""The estimated cost of a sweep: frames per case as the loop runs them, a measured cost for
every binning, oversampling and field of view a case can have, and a 90 000-case grid estimated at once."""

import time

import pytest

from soulctl.loop.schedule import OGTL_MAX_SETTLING_PERIODS, OGTL_SETTLING_PERIODS, OPTIMISER_OGTL
from soulctl.sweep.case import observation_for, optimisation_period_s
from soulctl.sweep.estimate import CALIBRATION_S, CASE_FIXED_S, FRAME_MS, case_cost, estimate, measured_cost
from soulctl.sweep.grid import parse_grid


def test_every_binning_and_oversampling_has_a_measured_cost():
    """Keys (binning, oversampling, sensing oversampling): the sampled field's (o, o) and SOUL's
    2.1" field's (o, max(o, 3)); the finer sensing pupil costs more, the loop's own grid too."""
    sampled = {(b, o, o) for b in (1, 2, 3, 4) for o in (1, 2, 3, 4)} - {(1, 1, 1), (2, 1, 1)}  # o = 1 only up to 90 modes
    wide = {(b, o, max(o, 3)) for b, o, _ in sampled}
    assert set(FRAME_MS) == set(CASE_FIXED_S) == set(CALIBRATION_S) == sampled | wide
    assert all(FRAME_MS[b, 4, 4] > FRAME_MS[b, 2, 2] for b in (1, 2, 3, 4))
    assert all(FRAME_MS[b, 2, 2] < FRAME_MS[b, 2, 3] for b in (1, 2, 3, 4))


def test_frames_of_a_case():
    case = {"magnitude": 16.6, "binning": 4, "oversampling": 1, "wfs_field": 0.0, "duration": 0.5}
    rate = observation_for(case).frame_rate_hz
    n, seconds, setup = case_cost(case)
    assert n == round(0.5 * rate) and seconds == pytest.approx(CASE_FIXED_S[4, 1, 1] + n * FRAME_MS[4, 1, 1] / 1e3)
    mgm, _, _ = case_cost({**case, "gain_method": "mgm"})
    trial, _, _ = case_cost({**case, "gain_method": "trial"})
    assert mgm > 3 * n and trial > 2 * n
    assert case_cost({"magnitude": 12.0, "oversampling": 1}) == (0, 0.0, None)  # 500 modes at o = 1: fails at once


def test_the_field_of_view_is_costed_at_its_sensing_oversampling():
    """SOUL's 2.1" (the default) reads on a sensing oversampling of 3, measured; 4" needs 6,
    costed as a loop at the measured 4 scaled by the FFT's area, (6/4)^2."""
    case = {"magnitude": 16.6, "binning": 4, "duration": 0.5}
    n, seconds, setup = case_cost(case)
    assert setup[:3] == (4, 2, 3) and seconds == pytest.approx(CASE_FIXED_S[4, 2, 3] + n * FRAME_MS[4, 2, 3] / 1e3)
    n, seconds, setup = case_cost({**case, "wfs_field": 4.0})
    assert setup[:3] == (4, 2, 6) and seconds == pytest.approx((CASE_FIXED_S[4, 4, 4] + n * FRAME_MS[4, 4, 4] / 1e3) * 2.25)
    assert measured_cost(CALIBRATION_S, 4, 2, 6) == pytest.approx(CALIBRATION_S[4, 4, 4] * 2.25)
    assert estimate([case, {**case, "wfs_field": 0.0}], 1).calibrations == 2


def test_the_paired_evaluation_is_counted_with_its_twelve_ogtl_updates():
    """Each of the two evaluation loops settles for OGTL_MAX_SETTLING_PERIODS updates when the
    optimiser runs OGTL (``schedule.evaluation_settle_s``), not for the run's least settling."""
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
