"""A look-up table from a sweep: the best binning and rate per magnitude, merged into rows."""

import math

import pytest

from soulctl.sweep.derive import best_per_magnitude, derived_table, lut_csv


def row(mag, binning, rate, strehl, status="ok"):
    return {"magnitude": mag, "binning": binning, "frame_rate": rate, "strehl": strehl, "status": status}


def test_best_rows_merge_into_look_up_table_rows():
    rows = [
        row(10.0, 1, 1700, 0.80),
        row(10.0, 2, 1000, 0.60),
        row(10.0, 1, 1000, 0.90, "diverged"),
        row(12.0, 1, 1000, 0.70),
        row(12.0, 2, 1000, 0.65),
        row(14.0, 2, 750, 0.40),
        row(14.0, 1, 500, math.nan),
        row(16.0, 2, 500, 0.20),
        row(16.0, 4, 250, 0.10),
    ]
    picks = best_per_magnitude(rows)
    assert [(p["magnitude"], p["binning"], p["frame_rate"]) for p in picks] == [
        (10.0, 1, 1700),
        (12.0, 1, 1000),
        (14.0, 2, 750),
        (16.0, 2, 500),
    ]
    table = derived_table(rows)
    assert [(r["r_min"], r["r_max"], r["binning"], r["frame_rate_max_hz"], r["frame_rate_min_hz"]) for r in table] == [
        (0.0, 13.0, 1, 1700, 1000),
        (13.0, 18.5, 2, 750, 500),
    ]
    assert table[0]["subapertures"] == 40 and table[1]["modes"] == 250
    text = lut_csv(table).splitlines()
    assert text[1] == "r_min,r_max,binning,subapertures,modes,frame_rate_max_hz,frame_rate_min_hz,modulation_lambda_over_d"
    assert text[2] == "0,13,1,40,500,1700,1000,3"


def test_rows_without_binning_take_the_look_up_tables():
    (pick,) = best_per_magnitude([{"magnitude": 16.0, "strehl": 0.2, "status": "ok", "binning": None, "frame_rate": None}])
    assert pick["binning"] == 3 and pick["frame_rate"] == pytest.approx(354.0)
