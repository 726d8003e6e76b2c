"""The results table: rows round-trip through the CSV, are appended one complete line at a time
and put in the grid's order at the end; --resume keeps the finished rows of the same grid,
runs failed ones again, checks every row and ignores an incomplete last line."""

import math
import os

import pytest

from soulctl.errors import InputError
from soulctl.sweep.case import failed_row
from soulctl.sweep.grid import case_id, parse_grid
from soulctl.sweep.results import ResultsTable, read_results, results_lock


def ok_row(case, strehl=0.5):
    return {**failed_row(case, ""), "status": "ok", "strehl": strehl, "tt_jitter_mas": 3.5, "residual_nm": 120.0}


def test_rows_round_trip_and_resume_keeps_finished_rows(tmp_path):
    cases = parse_grid({"magnitude": [12.0, 13.0, 14.0], "seeing": 0.8})
    ids = [case_id(c) for c in cases]
    table = ResultsTable(tmp_path / "results.csv", cases)
    table.open()
    table.add(ok_row(cases[1], 0.612345678901234))
    table.add(failed_row(cases[0], "ValueError: boom, with a comma\nand a second line"))
    lines = table.path.read_text().splitlines()
    assert len(lines) == 3 and lines[1].startswith(ids[1]) and lines[2].startswith(ids[0])  # finishing order
    table.write_ordered()
    lines = table.path.read_text().splitlines()
    assert len(lines) == 3 and lines[1].startswith(ids[0]) and lines[2].startswith(ids[1])  # the grid's order
    rows = ResultsTable.read_rows(table.path)
    assert rows[ids[1]]["strehl"] == 0.612345678901234 and rows[ids[1]]["seeing"] == 0.8 and rows[ids[1]]["noise"] is True
    assert rows[ids[0]]["reason"] == "ValueError: boom, with a comma and a second line" and math.isnan(rows[ids[0]]["strehl"])
    again = ResultsTable(table.path, cases)
    assert again.resume() == {ids[1]}  # the failed case runs again
    other_grid = ResultsTable(table.path, cases[2:])
    assert other_grid.resume() == set()  # rows of another grid are not this grid's ...
    other_grid.open()
    other_grid.add(failed_row(cases[2], "y"))
    other_grid.write_ordered()
    assert set(ResultsTable.read_rows(table.path)) == set(ids)  # ... but they stay in the file


def test_a_case_run_again_appends_a_row_and_the_last_row_counts(tmp_path):
    cases = parse_grid({"magnitude": [12.0, 13.0]})
    table = ResultsTable(tmp_path / "results.csv", cases)
    table.open()
    table.add(failed_row(cases[0], "x"))
    table.add(ok_row(cases[0]))
    table.close()
    assert len(table.path.read_text().splitlines()) == 3
    assert ResultsTable(table.path, cases).resume() == {case_id(cases[0])}


def _with_one_ok_row(tmp_path, cases) -> ResultsTable:
    """A results file holding the ok row of the first case (the start of the edits below)."""
    table = ResultsTable(tmp_path / "results.csv", cases)
    table.open()
    table.add(ok_row(cases[0]))
    table.close()
    return table


def test_an_incomplete_last_line_is_ignored_and_truncated(tmp_path):
    cases = parse_grid({"magnitude": [12.0, 13.0]})
    table = _with_one_ok_row(tmp_path, cases)
    whole = table.path.read_bytes()
    torn = ok_row(cases[1])
    table.path.write_bytes(whole + _line(torn)[:40])  # a crash in the middle of a write
    again = ResultsTable(table.path, cases)
    assert again.resume() == {case_id(cases[0])}
    assert any("line 3: an incomplete last row" in n for n in again.notes)
    again.open()
    assert table.path.read_bytes() == whole  # truncated at the last complete line
    again.add(torn)
    again.close()
    assert set(ResultsTable.read_rows(table.path)) == {case_id(c) for c in cases}


def _line(row):
    from soulctl.sweep.results import COLUMNS, csv_line

    return csv_line(row, COLUMNS).encode()


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda f: f.replace("0.5,3.5,120.0,ok", ",3.5,120.0,ok"), "line 2: status ok with an empty strehl"),
        (lambda f: f.replace("0.5,3.5,120.0,ok", "nan,3.5,120.0,ok"), "line 2: status ok with a non-finite strehl"),
        (lambda f: f.replace(",ok,", ",done,"), "line 2: status must be ok, diverged or failed, got 'done'"),
        (lambda f: f.replace(",1.0,8.0,25.0,", ",1.0,0.0,25.0,"), "line 2: wind must be in 0..100 m/s (> 0), got 0"),
        (lambda f: f.replace(",1.0,8.0,25.0,", ",1.0,9.0,25.0,"), "line 2: the row of case"),
        (lambda f: f.replace(",ok,", ",ok,,extra"), "line 2: 25 fields where the header has 24"),
        (lambda f: f.replace("case_id,", "case_id,band,", 1), "the column band appears more than once"),
        (lambda f: f.replace(",soulctl_version", ""), "lacks the columns soulctl_version"),
        (lambda f: f.replace(",wfs_field", ""), "lacks the column wfs_field: it was written before SOUL's 2.1"),
    ],
)
def test_edited_rows_are_refused_naming_the_line(tmp_path, edit, message):
    cases = parse_grid({"magnitude": [12.0]})
    table = _with_one_ok_row(tmp_path, cases)
    table.path.write_text(edit(table.path.read_text()))
    with pytest.raises(InputError, match=message.replace("(", r"\(").replace(")", r"\)").replace(".", r"\.")):
        ResultsTable(table.path, cases).resume()


def test_a_byte_order_mark_crlf_and_other_columns_are_accepted_and_kept(tmp_path):
    cases = parse_grid({"magnitude": [12.0, 13.0]})
    table = _with_one_ok_row(tmp_path, cases)
    lines = table.path.read_text().splitlines()
    text = "\r\n".join([lines[0] + ",notes", lines[1] + ",seen by me"]) + "\r\n"
    table.path.write_bytes(b"\xef\xbb\xbf" + text.encode())  # as a spreadsheet saves it
    again = ResultsTable(table.path, cases)
    assert again.resume() == {case_id(cases[0])}
    assert any("notes" in n for n in again.notes)
    again.open()
    again.add(ok_row(cases[1]))
    again.write_ordered()
    content = read_results(table.path)
    assert content.columns[-1] == "notes"
    assert [r["notes"] for r in content.rows.values()] == ["seen by me", ""]


def test_writes_leave_no_temporary_file(tmp_path):
    cases = parse_grid({"magnitude": [12.0, 13.0]})
    table = ResultsTable(tmp_path / "results.csv", cases)
    table.open()
    for c in cases:
        table.add(failed_row(c, "x"))
    table.write_ordered()
    assert [p.name for p in tmp_path.iterdir()] == ["results.csv"]


def test_one_writer_per_folder(tmp_path):
    with results_lock(tmp_path) as path:
        assert path.read_text().strip() == str(os.getpid())
        with pytest.raises(InputError, match=f"another soulctl sweep \\(process {os.getpid()}\\) is writing"):
            with results_lock(tmp_path):
                pass
    assert not path.exists()
    with results_lock(tmp_path):  # released
        pass
