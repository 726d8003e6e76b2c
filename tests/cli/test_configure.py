"""`soulctl configure`: output, files, and the one-line errors with exit status 2."""

import json
import subprocess
import sys

import pytest
from cli_run import run

from soulctl.observation import Observation


def test_json_is_one_object_with_the_configuration(capsys):
    status, out, err = run(["configure", "--mag", "13", "--json"], capsys)
    assert status == 0 and err == ""
    d = json.loads(out)
    assert d["wfs"]["binning"] == 2 and d["derived"]["subapertures"] == 20
    assert d["control"]["modes"] == 250 and d["control"]["tt_control"] == "iir"
    assert d["derived"]["delay_frames"] == pytest.approx(d["derived"]["delay_ms"] * 1e-3 * d["wfs"]["frame_rate_hz"], rel=1e-3)
    assert 4 < d["derived"]["photons_per_subaperture_per_frame"] < 8


def test_table_output(capsys):
    status, out, _ = run(["configure", "--mag", "16.9"], capsys)
    assert status == 0
    for text in ("binning", "10 x 10", "integrator", "loop delay", "photons", "16.5 < R <= 18.5"):
        assert text in out
    status, out, _ = run(["configure", "--mag", "3"], capsys)
    assert "0 <= R <= 10.5" in out


def test_out_writes_a_readable_toml(tmp_path, capsys):
    path = tmp_path / "obs.toml"
    status, out, _ = run(["configure", "--mag", "11.5", "--out", str(path), "--json"], capsys)
    assert status == 0
    assert Observation.read_toml(path).to_dict() == json.loads(out)


@pytest.mark.parametrize(
    "args, message",
    [
        (["--mag", "19"], "R magnitude 19 is outside the look-up table: accepted range 0 <= R <= 18.5"),
        (["--mag", "-1"], "accepted range 0 <= R <= 18.5"),
        (["--mag", "abc"], "--mag must be a number, got 'abc': accepted range 0 <= R <= 18.5"),
        (["--mag", "nan"], "accepted range 0 <= R <= 18.5"),
        (["--mag", "12", "--frobnicate"], "No such option: --frobnicate"),
        ([], "Missing option '--mag'"),
    ],
)
def test_bad_input_is_one_line_exit_2_nothing_written(args, message, tmp_path, capsys):
    path = tmp_path / "obs.toml"
    status, out, err = run(["configure", *args, "--out", str(path)], capsys)
    assert status == 2
    assert err.count("\n") == 1 and err.startswith("soulctl: error: ") and message in err
    assert not path.exists() and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "mag, shown", [("18.5000001", "R magnitude 18.5000001 is outside"), ("-0.0000001", "R magnitude -1e-07 is outside")]
)
def test_out_of_range_message_shows_the_value_given(mag, shown, capsys):
    status, _, err = run(["configure", "--mag", mag], capsys)
    assert status == 2 and shown in err


def test_minus_zero_is_zero(capsys):
    status, out, _ = run(["configure", "--mag", "-0", "--json"], capsys)
    assert status == 0 and '"magnitude_r": 0.0' in out


@pytest.mark.parametrize(
    "make_target",
    [
        lambda d: d / "a_file" / "obs.toml",  # parent is a file
        lambda d: d / ("x" * 250 + ".toml"),  # a valid name; a temporary named after it would be too long
    ],
)
def test_unwritable_out_is_one_line_exit_2(make_target, tmp_path, capsys):
    (tmp_path / "a_file").write_text("")
    target = make_target(tmp_path)
    status, _, err = run(["configure", "--mag", "12", "--out", str(target)], capsys)
    if status == 0:  # the long name is writable on this file system
        assert target.exists()
        return
    assert status == 2 and err.count("\n") == 1 and "--out" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


def test_paths_are_printed_verbatim(tmp_path, capsys):
    target = tmp_path / "y[bold].toml"
    status, out, _ = run(["configure", "--mag", "12", "--out", str(target)], capsys)
    assert status == 0 and target.exists() and f"written {target}" in out.replace("\n", "")


def test_out_into_missing_folder(tmp_path, capsys):
    status, _, err = run(["configure", "--mag", "12", "--out", str(tmp_path / "no" / "obs.toml")], capsys)
    assert status == 2 and "does not exist" in err


def test_console_script_has_no_traceback(tmp_path):
    """The installed entry point, as a user runs it (from another folder: ``python -c`` would
    otherwise import the source tree, which has no compiled core)."""
    proc = subprocess.run(
        [sys.executable, "-c", "from soulctl.cli.app import main; main()", "configure", "--mag", "x"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and proc.stderr.count("\n") == 1
    ok = subprocess.run(
        [sys.executable, "-c", "from soulctl.cli.app import main; main()", "configure", "--mag", "9.7"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert ok.returncode == 0 and "1700 Hz" in ok.stdout
