"""Sweep grids: the Cartesian product of the lists, stable case ids, and one-line errors."""

import pytest

from soulctl.errors import InputError
from soulctl.sweep.grid import case_id, parse_grid


def test_lists_are_axes_in_the_files_order():
    cases = parse_grid({"magnitude": [12, 16.5], "seeing": [0.8, 1.2, 1.6], "binning": 4, "seed": 3})
    assert len(cases) == 6
    assert cases[0] == {"magnitude": 12.0, "seeing": 0.8, "binning": 4, "seed": 3}
    assert [c["seeing"] for c in cases[:3]] == [0.8, 1.2, 1.6] and cases[3]["magnitude"] == 16.5
    assert isinstance(cases[0]["magnitude"], float) and isinstance(cases[0]["binning"], int)


def test_ranges_are_those_of_soulctl_ranges():
    from soulctl import ranges, tables
    from soulctl.sweep.grid import PARAMETERS

    assert PARAMETERS["seeing"].range is ranges.SEEING_ARCSEC and PARAMETERS["wind"].range is ranges.WIND_M_S
    assert PARAMETERS["L0"].range is ranges.OUTER_SCALE_M and PARAMETERS["duration"].range is ranges.DURATION_S
    assert PARAMETERS["frame_rate"].range is ranges.FRAME_RATE_HZ and PARAMETERS["seed"].range is ranges.SEED
    assert PARAMETERS["oversampling"].range is ranges.OVERSAMPLING
    m = PARAMETERS["magnitude"].range
    assert (m.lo, m.hi) == tables.magnitude_range(tables.magnitude_table())


def test_case_ids_depend_on_the_parameters_only():
    a = parse_grid({"magnitude": [12, 13], "seeing": 1.0})
    b = parse_grid({"seeing": 1.0, "magnitude": [13, 12]})
    assert {case_id(c) for c in a} == {case_id(c) for c in b} and len({case_id(c) for c in a}) == 2


@pytest.mark.parametrize(
    "grid, message",
    [
        ({}, "is empty"),
        ({"seeing": 1.0}, "needs magnitude"),
        ({"magnitude": 12, "colour": "red"}, "unknown parameter colour"),
        ({"magnitude": []}, "magnitude is an empty list"),
        ({"magnitude": 12, "seeing": [1.0, -1.0]}, "seeing must be in 0.05..10 arcsec, got -1"),
        ({"magnitude": 18.6}, "magnitude must be in 0..18.5, got 18.6"),
        ({"magnitude": 12, "wind": 0}, "wind must be in 0..100 m/s (> 0), got 0"),
        ({"magnitude": 12, "L0": 0.1}, "L0 must be in 0.5..10000 m, got 0.1"),
        ({"magnitude": 12, "seeing": float("nan")}, "seeing must be in 0.05..10 arcsec, got nan"),
        ({"magnitude": 12, "oversampling": 5}, "oversampling must be in 1..4, got 5"),
        ({"magnitude": 12, "binning": 2.5}, "binning must be 1, 2, 3 or 4"),
        ({"magnitude": 12, "noise": "yes"}, "noise must be true or false"),
        ({"magnitude": 12, "seed": True}, "seed must be"),
        ({"magnitude": 12, "gain_method": "auto"}, "gain_method must be default, mgm or trial"),
    ],
)
def test_bad_grids_name_the_problem(grid, message):
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)").replace(".", r"\.")):
        parse_grid(grid)


def test_the_mirror_model_is_an_axis():
    """A sweep compares the two influence-function models by their run description field."""
    cases = parse_grid({"magnitude": 16.5, "mirror.influence": ["gaussian", "thin-plate"]})
    assert [c["mirror.influence"] for c in cases] == ["gaussian", "thin-plate"]
    with pytest.raises(InputError, match="mirror.influence must be one of gaussian, thin-plate"):
        parse_grid({"magnitude": 16.5, "mirror.influence": ["gaussian", "bessel"]})
