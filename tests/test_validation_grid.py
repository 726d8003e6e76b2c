"""The magnitude grid's judgement (validation/optimize_magnitudes.py): its checks are the
issue's acceptance criteria, and its rows are combined across sessions by code fingerprint."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

_PATH = Path(__file__).resolve().parent.parent / "validation" / "optimize_magnitudes.py"


@pytest.fixture(scope="module")
def grid(validation):
    return validation("optimize_magnitudes")


def _row(variant: str, before: float, after: float, seed: int = 1, code: str = "abc", diverged_at=None) -> dict:
    windows = {"window_s": 1.0, "before": [before], "after": [after], "mean_before": before, "mean_after": after, "standard_error": 0.0}
    return {
        "mag": 18.5,
        "seeing": 0.6,
        "seed": seed,
        "variant": variant,
        "diverged_at": diverged_at,
        "before": 0.0,  # optimize's own window: the checks must use the windows' means
        "after": 0.0,
        "safety_restores": 0,
        "windows": windows,
        "code": code,
    }


def test_the_checks_are_the_issues_criteria(grid):
    rows = grid.checks(
        [
            _row("mgm+ogtl", 0.120, 0.111),  # after within 0.01 of before, but 0.011 below trial's
            _row("trial+ogtl", 0.120, 0.122),
            _row("mgm", 0.100, 0.0895),  # 0.0105 below before, within 0.01 of trial's
            _row("trial", 0.100, 0.095),
        ]
    )
    flags = {r["variant"]: (r["ok_after_before"], r["ok_mgm_vs_trial"]) for r in rows}
    assert flags == {"mgm+ogtl": (True, False), "trial+ogtl": (True, None), "mgm": (False, True), "trial": (True, None)}
    assert [r["variant"] for r in grid.misses(rows)] == ["mgm+ogtl", "mgm"]
    diverged = grid.checks([{**_row("trial", 0.1, 0.1), "diverged_at": 12, "after": None}])
    assert grid.misses(diverged) and not diverged[0]["ok_divergence"]


def test_rows_are_combined_by_code_fingerprint(grid, tmp_path):
    a, b = tmp_path / "a.jsonl", tmp_path / "b.jsonl"
    a.write_text("\n".join(json.dumps(r) for r in (_row("mgm", 0.1, 0.2, code="old"), _row("trial", 0.1, 0.1))) + "\n")
    b.write_text(json.dumps(_row("mgm", 0.1, 0.3, code="abc")) + "\n" + json.dumps(_row("mgm", 0.1, 0.4, code="abc")) + "\n")
    rows = grid.read_rows([a, b], {"abc"})
    assert sorted((r["variant"], r["windows"]["mean_after"]) for r in rows) == [("mgm", 0.3), ("trial", 0.1)]  # the first of a case
    assert len(grid.read_rows([a, b], None)) == 2
    assert len(grid.read_rows([a, b], {"abc", "old"})) == 2 and grid.read_rows([a, b], {"old"})[0]["windows"]["mean_after"] == 0.2
    assert grid.read_rows([a, b], {"abc"}, wanted={(18.5, 0.6, 1, "trial")})[0]["variant"] == "trial"
    wanted = {(18.5, 0.6, 1, "mgm"), (18.5, 0.6, 1, "trial"), (18.5, 1.0, 2, "mgm")}
    assert grid.not_run(wanted, rows) == 'not run on this code: 1 points: R18.5 1" s2'


def test_rows_of_code_before_the_give_up_fixes_count_when_too_few_restores_for_a_give_up(grid, tmp_path):
    a = tmp_path / "a.jsonl"
    few, many = (_row("mgm", 0.1, 0.2, seed=s, code="old") for s in (1, 2))
    few["safety_restores"], many["safety_restores"] = grid.FEWEST_RESTORES - 1, grid.FEWEST_RESTORES
    a.write_text("\n".join(json.dumps(r) for r in (few, many, _row("trial", 0.1, 0.1, code="other"))) + "\n")
    assert grid.FEWEST_RESTORES == 6
    assert [r["seed"] for r in grid.read_rows([a], {"abc"}, before_give_up=frozenset({"old"}))] == [1]
    assert not grid.read_rows([a], {"abc"}) and len(grid.read_rows([a], {"old"}, before_give_up=frozenset({"old"}))) == 2


def test_rows_without_ogtl_of_code_that_changed_only_ogtl_count(grid, tmp_path):
    a = tmp_path / "a.jsonl"
    a.write_text("\n".join(json.dumps(_row(v, 0.1, 0.2, code="old")) for v in ("mgm", "trial+ogtl", "mgm+ogtl")) + "\n")
    assert [r["variant"] for r in grid.read_rows([a], {"abc"}, without_ogtl=frozenset({"old"}))] == ["mgm"]
    assert not grid.read_rows([a], {"abc"}, without_ogtl=frozenset({"other"}))


def test_trial_rows_of_code_that_changed_only_mgm_count(grid, tmp_path):
    a = tmp_path / "a.jsonl"
    a.write_text("\n".join(json.dumps(_row(v, 0.1, 0.2, code="old")) for v in ("mgm", "trial+ogtl", "mgm+ogtl", "trial")) + "\n")
    assert [r["variant"] for r in grid.read_rows([a], {"abc"}, without_mgm=frozenset({"old"}))] == ["trial+ogtl", "trial"]
    both = grid.read_rows([a], {"abc"}, without_mgm=frozenset({"old"}), without_ogtl=frozenset({"old"}))
    assert [r["variant"] for r in both] == ["trial"]
    newer = _row("trial", 0.1, 0.15, code="abc")  # the current code's row of a case takes its place
    a.write_text(a.read_text() + json.dumps(newer) + "\n")
    rows = grid.read_rows([a], {"abc"}, without_mgm=frozenset({"old"}))
    assert sorted((r["variant"], r["code"]) for r in rows) == [("trial", "abc"), ("trial+ogtl", "old")]


def test_rows_the_wait_for_a_calibrated_k_cannot_reach_count(grid, tmp_path):
    """Rows of code before the optimisers waited for OGTL's calibrated k count without OGTL, or
    where k had left 1 by the end of *before* (OGTL raises k only on an estimate it acted on);
    of two admitted older rows of a case the later in the file (the newer run) counts."""
    a = tmp_path / "a.jsonl"
    rows = [_row(v, 0.1, 0.2, code="old") | {"sensitivities": [k, k]} for v, k in (("mgm", 1.0), ("mgm+ogtl", 1.0), ("trial+ogtl", 2.3))]
    a.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    assert [r["variant"] for r in grid.read_rows([a], {"abc"}, calibrated_k=frozenset({"old"}))] == ["mgm", "trial+ogtl"]
    newer = _row("trial+ogtl", 0.1, 0.3, code="newer") | {"sensitivities": [2.1, 2.1]}
    a.write_text(a.read_text() + json.dumps(newer) + "\n")
    kept = grid.read_rows([a], {"abc"}, calibrated_k=frozenset({"old", "newer"}))
    assert [(r["variant"], r["code"]) for r in kept] == [("mgm", "old"), ("trial+ogtl", "newer")]


def test_rows_without_a_restore_of_code_that_changed_only_the_restore_count(grid, tmp_path):
    """A code named for two differences (OGTL and the restores) needs both conditions."""
    a = tmp_path / "a.jsonl"
    rows = [_row(v, 0.1, 0.2, seed=s, code="old") for v in ("mgm", "mgm+ogtl") for s in (1, 2)]
    for r in rows[1::2]:
        r["safety_restores"] = 1
    a.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    kept = grid.read_rows([a], {"abc"}, without_restores=frozenset({"old"}))
    assert sorted((r["variant"], r["seed"]) for r in kept) == [("mgm", 1), ("mgm+ogtl", 1)]
    both = grid.read_rows([a], {"abc"}, without_ogtl=frozenset({"old"}), without_restores=frozenset({"old"}))
    assert [(r["variant"], r["seed"]) for r in both] == [("mgm", 1)]


def test_the_fingerprint_changes_with_any_source_or_table_and_nothing_else(grid, tmp_path):
    package, tables = tmp_path / "soulctl", tmp_path / "tables"
    (package / "loop").mkdir(parents=True)
    tables.mkdir()
    (package / "loop" / "optimize.py").write_text("PERIOD = 1.0\n")
    (package / "notes.txt").write_text("not code")
    (tables / "photometry.toml").write_text("zero_point = 1\n")
    first = grid.code_fingerprint(package, tables)
    assert len(first) == 12 and grid.code_fingerprint(package, tables) == first
    (package / "notes.txt").write_text("still not code")
    assert grid.code_fingerprint(package, tables) == first
    (package / "loop" / "optimize.py").write_text("PERIOD = 1.1\n")
    second = grid.code_fingerprint(package, tables)
    (tables / "photometry.toml").write_text("zero_point = 2\n")
    assert len({first, second, grid.code_fingerprint(package, tables)}) == 3
    assert len(grid.code_fingerprint()) == 12  # the installed package's


def test_every_rate_gets_the_frames_of_six_windows_at_750_hz(grid):
    assert [grid.windows_for(r) for r in (1700, 750, 500, 250, 100)] == [6, 6, 9, 18, 45]


def test_the_shared_evaluation_takes_what_evaluate_takes(grid):
    """``SharedEvaluations`` stands in for ``optimize.evaluate``: the same parameters, or a
    grid run fails at its first evaluation."""
    import inspect

    from soulctl.loop import optimize

    with grid.SharedEvaluations():
        wrapped = list(inspect.signature(optimize.evaluate).parameters)
    assert wrapped == list(inspect.signature(optimize.evaluate).parameters)


def test_the_split_swaps_one_group_at_a_time(validation):
    split = validation("mgm_split")
    initial, final = np.full(250, 0.5), np.full(250, 0.2)
    sets = split.gain_sets(initial, final)
    tt = sets["initial with MGM's tip-tilt"]
    assert np.all(tt[:2] == 0.2) and np.all(tt[2:] == 0.5)
    mid = sets["MGM's with the initial modes 3-120"]
    assert np.all(mid[2:120] == 0.5) and np.all(mid[:2] == 0.2) and np.all(mid[120:] == 0.2)
    assert np.all(sets["initial"] == initial) and np.all(sets["MGM's"] == final)
    assert initial[0] == 0.5 and final[0] == 0.2  # the swaps copy, not alias


def test_the_split_pairs_window_by_window(validation):
    split = validation("mgm_split")
    reference = [0.40, 0.45, 0.38, 0.47]  # the turbulence moves every window; the pairing removes it
    rows = [
        {"gains": "initial", "windows": reference},
        {"gains": "lower", "windows": [w - 0.01 for w in reference]},
        {"gains": "noisy", "windows": [w + d for w, d in zip(reference, (0.01, -0.01, 0.01, -0.01))]},
    ]
    (d0, e0), (d1, e1), (d2, e2) = split.paired_differences(rows)
    assert d0 == 0 and e0 == 0
    assert d1 == pytest.approx(-0.01) and e1 == pytest.approx(0, abs=1e-12)
    assert d2 == pytest.approx(0, abs=1e-12) and e2 == pytest.approx(0.01 * np.sqrt(4 / 3) / np.sqrt(4))  # ddof = 1
