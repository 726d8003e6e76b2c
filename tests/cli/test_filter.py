"""`soulctl filter analyze|design`: output, exit status, plots, and one-line errors."""

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest
from cli_run import run

PAPER_FIGURE = [
    "filter",
    "analyze",
    "--rate",
    "1700,1700,1000",
    "--control",
    "iir,int,int",
    "--gain",
    "0.69,0.21,0.39",
    "--system",
    "soul,soul,flao",
    "--label",
    "SOUL-IIR,SOUL-INT,FLAO-INT",
]


def test_analyze_json_compares_controllers(capsys):
    status, out, err = run([*PAPER_FIGURE, "--json"], capsys)
    assert status == 0 and err == ""
    d = json.loads(out)
    assert d["stable"] is True and [c["label"] for c in d["controllers"]] == ["SOUL-IIR", "SOUL-INT", "FLAO-INT"]
    iir, flao = d["controllers"][0], d["controllers"][2]
    assert iir["zeros"] == [-0.31, 0.69, 0.698, 0.705] and iir["rejection_13hz"] == pytest.approx(0.11, abs=0.015)
    assert flao["delay_ms"] == pytest.approx(3.1) and flao["delay_frames"] == pytest.approx(3.1)
    for key in ("gain_margin", "phase_margin_deg", "modulus_margin", "max_stable_gain", "noise_127hz", "bandwidth_hz"):
        assert isinstance(iir[key], float)


def test_analyze_table_and_plot(tmp_path, capsys):
    png = tmp_path / "tf.png"
    status, out, _ = run([*PAPER_FIGURE, "--plot", str(png)], capsys)
    assert status == 0
    for text in ("SOUL-IIR", "gain margin", "phase margin", "|S(13 Hz)|", "|T(127 Hz)|", "stable", "written"):
        assert text in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_analyze_given_roots_delay_and_chi(capsys):
    status, out, _ = run(
        [
            "filter",
            "analyze",
            "--rate",
            "1000",
            "--gain",
            "0.5",
            "--zeros",
            "0.5",
            "--poles",
            "1,0.2",
            "--delay-ms",
            "2",
            "--chi",
            "0.5",
            "--json",
        ],
        capsys,
    )
    c = json.loads(out)["controllers"][0]
    assert status == 0 and c["poles"] == [1.0, 0.2] and c["delay_frames"] == pytest.approx(2.0)
    assert c["optical_gain"] == 0.5


def test_analyze_leaky(capsys):
    status, out, _ = run(
        [
            "filter",
            "analyze",
            "--rate",
            "500",
            "--control",
            "leaky",
            "--forgetting",
            "0.9",
            "--gain",
            "0.5",
            "--delay-frames",
            "1.5",
            "--json",
        ],
        capsys,
    )
    c = json.loads(out)["controllers"][0]
    assert status == 0 and c["poles"] == [0.9]
    # |S| at 13 Hz from the loop written out: C(z) = g / (1 - a z^-1), P(z) = z^-1.5 as the delay
    # line's interpolation 0.5 z^-1 + 0.5 z^-2
    z1 = np.exp(-2j * np.pi * 13.0 / 500.0)
    loop_13 = 0.5 / (1 - 0.9 * z1) * (0.5 * z1 + 0.5 * z1**2)
    assert c["rejection_13hz"] == pytest.approx(abs(1 / (1 + loop_13)), rel=1e-9)


def test_unstable_loop_exit_3_with_figures(capsys):
    status, out, err = run(["filter", "analyze", "--rate", "1700", "--control", "int", "--gain", "0.6", "--json"], capsys)
    assert status == 3
    c = json.loads(out)["controllers"][0]
    assert c["stable"] is False and c["gain_margin"] < 1 and c["max_stable_gain"] == pytest.approx(0.523, abs=1e-3)
    # no closed-loop figure for a loop without a steady state: null with the reason, n/a in the table
    for name in ("modulus_margin", "rejection_13hz", "noise_127hz", "rejection_bandwidth_hz", "bandwidth_hz"):
        assert c[name] is None and "unstable" in c["not_available"][name]
    status, out, _ = run(["filter", "analyze", "--rate", "1700", "--control", "int", "--gain", "0.6"], capsys)
    assert status == 3 and "UNSTABLE" in out
    assert "n/a (unstable)" in [line for line in out.splitlines() if "|S(13 Hz)|" in line][0]


@pytest.mark.parametrize(
    "args, message",
    [
        (["--rate", "0", "--gain", "0.5"], "--rate must be in 1..100000 Hz, got 0"),
        (["--rate", "-5", "--gain", "0.5"], "--rate must be in 1..100000 Hz, got -5"),
        (["--rate", "1000", "--gain", "abc"], "--gain must be a number in 0.0001..1000, got 'abc'"),
        (["--rate", "1000", "--gain", "0.5", "--delay-frames", "-1"], "--delay-frames must be in 0..50 frames, got -1"),
        (["--rate", "1000", "--gain", "0.5", "--delay-ms", "-2"], "--delay-ms must be in 0..50000 ms, got -2"),
        (["--rate", "1000", "--gain", "0.5", "--delay-ms", "2", "--delay-frames", "2"], "not both"),
        (["--rate", "1000", "--gain", "0.5", "--zeros", "0.3"], "--poles needs at least one pole"),
        (["--rate", "1000", "--gain", "0.5", "--poles", "1,abc"], "--poles must be numbers"),
        (["--rate", "1000", "--gain", "0.5", "--poles", "0.5+0.1j"], "conjugate pairs"),
        (["--rate", "1000", "--gain", "0.5", "--control", "pid"], "--control must be iir, int or leaky"),
        (["--rate", "1000,1700", "--gain", "0.5,0.2,0.3"], "--rate has 2 values but --gain has 3: give one value or 3"),
        (["--rate", "1000", "--gain", "0.5", "--forgetting", "1.5", "--control", "leaky"], "--forgetting must be in 0..1, got 1.5"),
        (["--rate", "1000", "--gain", "0.5", "--plot", "tf.txt"], "--plot must end in .png"),
        (["--rate", "1000", "--gain", "0.5", "--system", "keck"], "--system must be soul or flao"),
        (["--rate", "1000"], "Missing option '--gain'"),
    ],
)
def test_analyze_bad_input_is_one_line_exit_2(args, message, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    status, out, err = run(["filter", "analyze", *args], capsys)
    assert status == 2 and out == ""
    assert err.count("\n") == 1 and err.startswith("soulctl: error: ") and message in err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "args, message",
    [
        (["--epsilon", "1.5"], "--epsilon must be in 0..1 (> 0, < 1), got 1.5"),
        (["--epsilon", "0"], "--epsilon must be in 0..1 (> 0, < 1), got 0"),
        (["--rate", "0"], "--rate must be in 100..2000 Hz, got 0"),
        (["--rate", "1700,1700"], "twice"),
        (["--delay-ms", "-1"], "--delay-ms must be a number >= 0 ms, got -1"),
        (["--seeing", "0"], "--seeing must be in 0.05..10 arcsec, got 0"),
        (["--vibrations", "missing.toml"], "vibration file not found"),
        (["--noise", "-1"], "--noise must be in 0..10000 mas, got -1"),
    ],
)
def test_design_bad_input_is_one_line_exit_2(args, message, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    status, out, err = run(["filter", "design", *args, "--out", "roots.csv"], capsys)
    assert status == 2 and out == ""
    assert err.count("\n") == 1 and message in err
    assert not (tmp_path / "roots.csv").exists()


def test_design_json_out_plot_and_configure_roots(tmp_path, capsys):
    roots, png = tmp_path / "roots.csv", tmp_path / "design.png"
    status, out, err = run(["filter", "design", "--rate", "1000", "--json", "--out", str(roots), "--plot", str(png), "--seed", "3"], capsys)
    assert status == 0
    d = json.loads(out)
    (design,) = d["designs"]
    assert design["rate_hz"] == 1000 and design["iir"]["poles"][-1] == 1.0 and design["runtime_s"] > 0
    assert design["integrator"]["zeros"] == [] and design["table"]["zeros"] == [0.337, 0.345, 0.345, 0.353]
    assert d["seed"] == 3 and png.read_bytes()[:4] == b"\x89PNG"
    # configure takes the designed filter for a star whose frame rate is nearest to 1000 Hz
    status, out, _ = run(["configure", "--mag", "13", "--roots", str(roots), "--json"], capsys)
    c = json.loads(out)["control"]
    assert status == 0 and c["tt_filter_rate_hz"] == 1000
    assert c["tt_zeros"] == pytest.approx(design["iir"]["zeros"], abs=1e-4)
    # ... and its designed gain, not the paper's 0.69 (the filter and its gain are one design)
    assert c["tt_gain"] == pytest.approx(design["iir"]["gain"], abs=1e-4)


def test_a_designed_gain_is_the_runs_tip_tilt_gain(tmp_path, capsys, monkeypatch):
    """configure --roots carries a roots table's gain column into the observation file, and a
    run of that file starts Tip/Tilt at it; the paper's table (no gain column) keeps 0.69."""
    monkeypatch.chdir(tmp_path)
    header = "frame_rate_hz,zero1,zero2,zero3,zero4,pole1,pole2,pole3,pole4"
    Path("r.csv").write_text(f"{header},gain\n1700,-0.31,0.69,0.698,0.705,0.042,0.102,0.954,1.0,0.512\n")
    Path("paper.csv").write_text(f"{header}\n1700,-0.31,0.69,0.698,0.705,0.042,0.102,0.954,1.0\n")
    for roots, gain in (("r.csv", 0.512), ("paper.csv", 0.69)):
        status, _, _ = run(["configure", "--mag", "9.7", "--roots", roots, "--out", "obs.toml"], capsys)
        assert status == 0
        status, out, _ = run(["loop", "run", "--config", "obs.toml", "--print-config"], capsys)
        assert status == 0 and tomllib.loads(out)["control"]["gains"][0] == gain


@pytest.mark.parametrize(
    "text, message",
    [
        ("frame_rate_hz,zero1\n1000,0.1\n", "lacks the columns"),
        ("frame_rate_hz,zero1,zero2,zero3,zero4,pole1,pole2,pole3,pole4\n1000,a,0,0,0,0,0,0,1\n", "must hold 9 numbers"),
        ("frame_rate_hz,zero1,zero2,zero3,zero4,pole1,pole2,pole3,pole4\n1000,0,0,0,0,0,0,1.5,1\n", "poles must be in -1..1"),
        ("frame_rate_hz,zero1,zero2,zero3,zero4,pole1,pole2,pole3,pole4\n", "no rows"),
        ("frame_rate_hz,zero1,zero2,zero3,zero4,pole1,pole2,pole3,pole4,gain\n1000,0,0,0,0,0,0,0,1,0\n", "the gain must be in 0..10 (> 0)"),
        ("frame_rate_hz,zero1,zero2,zero3,zero4,pole1,pole2,pole3,pole4,gain\n1000,0,0,0,0,0,0,0,1,nan\n", "the gain must be in"),
    ],
)
def test_configure_malformed_roots_exit_2(text, message, tmp_path, capsys):
    p = tmp_path / "roots.csv"
    p.write_text(text)
    status, out, err = run(["configure", "--mag", "9", "--roots", str(p)], capsys)
    assert status == 2 and message in err and err.count("\n") == 1


def test_a_piped_table_keeps_its_rows_on_one_line(tmp_path, capsys, monkeypatch):
    """Into a pipe (no terminal, no COLUMNS) a table is laid out wider than rich's 80 columns,
    so that a row greps whole (at 80 this row's source wrapped after 'filter')."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("COLUMNS", raising=False)
    header = "frame_rate_hz,zero1,zero2,zero3,zero4,pole1,pole2,pole3,pole4,gain"
    Path("designed_roots_of_a_night.csv").write_text(f"{header}\n1700,-0.31,0.69,0.698,0.705,0.042,0.102,0.954,1.0,0.512\n")
    status, out, _ = run(["configure", "--mag", "9.7", "--roots", "designed_roots_of_a_night.csv"], capsys)
    assert status == 0
    assert any("0.512" in line and "designed with the filter (designed_roots_of_a_night.csv)" in line for line in out.splitlines())
    assert max(len(line) for line in out.splitlines()) > 80
