"""The results table: rows round-trip through the CSV, every write is whole, --resume keeps
the finished rows of the same grid and runs failed ones again."""

import math

import pytest

from soulctl.errors import InputError
from soulctl.sweep.case import failed_row
from soulctl.sweep.grid import case_id, parse_grid
from soulctl.sweep.results import ResultsTable


def test_rows_round_trip_and_resume_keeps_finished_rows(tmp_path):
    cases = parse_grid({"magnitude": [12.0, 13.0, 14.0], "seeing": 0.8})
    ids = [case_id(c) for c in cases]
    table = ResultsTable(tmp_path / "results.csv", ids)
    ok = {**failed_row(cases[1], ""), "status": "ok", "strehl": 0.612345678901234, "tt_jitter_mas": 3.5, "residual_nm": 120.0}
    table.add(ok)
    table.add(failed_row(cases[0], "ValueError: boom, with a comma"))
    lines = table.path.read_text().splitlines()
    assert len(lines) == 3 and lines[1].startswith(ids[0]) and lines[2].startswith(ids[1])  # the grid's order
    rows = ResultsTable.read_rows(table.path)
    assert rows[ids[1]]["strehl"] == 0.612345678901234 and rows[ids[1]]["seeing"] == 0.8 and rows[ids[1]]["noise"] is True
    assert rows[ids[0]]["reason"] == "ValueError: boom, with a comma" and math.isnan(rows[ids[0]]["strehl"])
    again = ResultsTable(table.path, ids)
    assert again.resume() == {ids[1]}  # the failed case runs again
    other_grid = ResultsTable(table.path, ids[2:])
    assert other_grid.resume() == set()  # rows of another grid are not this grid's ...
    other_grid.add(failed_row(cases[2], "y"))
    assert set(ResultsTable.read_rows(table.path)) == set(ids)  # ... but they stay in the file


def test_a_malformed_results_file_is_an_input_error(tmp_path):
    path = tmp_path / "results.csv"
    path.write_text("case_id,magnitude,seed\nabc,15.0\n")
    with pytest.raises(InputError, match="line 2: not a row of a sweep"):
        ResultsTable.read_rows(path)


def test_writes_leave_no_temporary_file(tmp_path):
    cases = parse_grid({"magnitude": [12.0, 13.0]})
    table = ResultsTable(tmp_path / "results.csv", [case_id(c) for c in cases])
    for c in cases:
        table.add(failed_row(c, "x"))
    assert [p.name for p in tmp_path.iterdir()] == ["results.csv"]
