"""`soulctl loop run`: results, telemetry, figures, divergence (exit 3) and one-line errors."""

import json

import numpy as np
import pytest
from cheap import CHEAP_PYRAMID

from soulctl.cli.app import main
from soulctl.sweep.case import run_case
from soulctl.telemetry.formats import read_telemetry

FAINT = ["loop", "run", "--mag", "16.5", *CHEAP_PYRAMID, "--duration", "0.3"]


def run(args, capsys, cache_dir):
    status = main([*args, "--cache-dir", str(cache_dir)])
    out, err = capsys.readouterr()
    return status, out, err


def test_json_result_and_same_seed_same_numbers(capsys, cache_dir):
    status, out, err = run([*FAINT, "--json", "--seed", "3"], capsys, cache_dir)
    assert status == 0, err
    d = json.loads(out)
    m = d["metrics"]
    assert 0 < m["strehl"] < 1 and m["tt_jitter_mas"] > 0 and m["residual_nm"] > 0
    assert d["configuration"]["observation"]["wfs"]["binning"] == 3 and d["configuration"]["frames"] == 75
    assert d["diverged_at_frame"] is None and "misregistration_stability" not in d
    status, out2, _ = run([*FAINT, "--json", "--seed", "3"], capsys, cache_dir)
    assert json.loads(out2)["metrics"] == m
    status, out3, _ = run([*FAINT, "--json", "--seed", "4"], capsys, cache_dir)
    assert json.loads(out3)["metrics"]["strehl"] != m["strehl"]


def test_table_telemetry_and_figures(tmp_path, capsys, cache_dir):
    h5 = tmp_path / "tm.h5"
    status, out, _ = run(
        [*FAINT, "--band", "Ks", "--telemetry", str(h5), "--telemetry-fields", "all", "--plot", str(tmp_path)], capsys, cache_dir
    )
    assert status == 0
    for text in ("Strehl ratio (Ks", "Tip/Tilt jitter", "pseudo-open loop", "residual wavefront error"):
        assert text in out
    arrays, attrs = read_telemetry(h5)
    assert arrays["slopes"].shape[0] == 75 and arrays["measured_modes"].shape == (75, 90) and arrays["gains"].shape == (90,)
    assert attrs["rate_hz"] == 250.0 and attrs["diverged_at"] == -1 and attrs["configuration"]["band"] == "Ks"
    np.testing.assert_allclose(arrays["frame_time_s"][:3], [0, 0.004, 0.008])
    for name in ("psf.png", "jitter.png", "modal_variance.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_divergence_exits_3_and_keeps_the_telemetry(tmp_path, capsys, cache_dir):
    h5 = tmp_path / "div.h5"
    status, out, err = run([*FAINT, "--gains", "4,4,4", "--allow-unstable", "--seeing", "0.5", "--telemetry", str(h5)], capsys, cache_dir)
    assert status == 3
    assert "loop diverged at frame" in err and "Traceback" not in err
    arrays, attrs = read_telemetry(h5)
    assert attrs["diverged_at"] >= 0 and arrays["residual_rms_nm"].shape[0] == attrs["diverged_at"] + 1


def test_a_loop_lost_to_misregistration_exits_3_with_its_figures(tmp_path, capsys, cache_dir):
    """Two pitches of shift leave eigenmodes of R D' unstable: the loop saturates instead of
    diverging, and is reported lost (exit 3) with its figures and telemetry; half a pitch is not."""
    h5 = tmp_path / "lost.h5"
    status, out, err = run([*FAINT, "--misregistration", "2,0", "--json", "--telemetry", str(h5)], capsys, cache_dir)
    assert status == 3 and "the loop is lost" in err and "eigenmodes are unstable" in err and "Traceback" not in err
    d = json.loads(out)
    c = d["misregistration_stability"]
    assert not c["stable"] and c["unstable"] > 0 and c["margin"] < 1 and c["largest_pole"] > 1
    assert d["diverged_at_frame"] is None and d["metrics"]["strehl"] is not None
    assert read_telemetry(h5)[1]["diverged_at"] == -1
    status, out, err = run([*FAINT, "--misregistration", "2,0"], capsys, cache_dir)  # the table too
    assert status == 3 and "Strehl ratio" in out and "mis-registration" in out and "the loop is lost" in err
    status, out, err = run([*FAINT, "--misregistration", "0.5,0", "--json"], capsys, cache_dir)
    assert status == 0, err
    c = json.loads(out)["misregistration_stability"]
    assert c["stable"] and c["unstable"] == 0 and c["margin"] > 1


def test_a_sweep_case_lost_to_misregistration_is_diverged_with_its_figures(cache_dir):
    """The sweep's rule is `loop run`'s: status "diverged" with the reason, and the lost loop's
    figures kept (a Strehl-against-shift sweep keeps its curve)."""
    case = {"magnitude": 16.5, "oversampling": 1, "wfs_field": 0.0, "duration": 0.3, "misregistration.shift_x_pitch": 2.0}
    row = run_case(case, cache_dir=str(cache_dir))
    assert row["status"] == "diverged" and row["reason"].startswith("the loop is lost"), row
    assert 0 < row["strehl"] < 1 and row["residual_nm"] > 0
    assert run_case(case | {"misregistration.shift_x_pitch": 0.5}, cache_dir=str(cache_dir))["status"] == "ok"


def test_unstable_gains_are_refused_with_the_maximum_stable_gain(capsys, cache_dir):
    status, out, err = run(["loop", "run", "--tt-control", "int", "--gains", "0.45,0.2,0.2"], capsys, cache_dir)
    assert status == 2 and "maximum stable gain 0.340" in err and "--allow-unstable" in err


@pytest.mark.parametrize(
    "args, message",
    [
        (["--band", "K"], "unknown band 'K': accepted R, I, J, H, FeII, Ks"),
        (["--duration", "0"], "--duration must be in 0..600"),
        (["--duration", "-1"], "--duration must be in 0..600"),
        (["--seeing", "0"], "--seeing must be in 0.05..10 arcsec"),
        (["--seeing", "0.01"], "--seeing must be in 0.05..10 arcsec"),
        (["--wind", "-3"], "--wind must be in 0..100"),
        (["--L0", "0"], "--L0 must be in 0.5..10000 m"),
        (["--gains", "a,b,c"], "--gains must be TT,MID,HIGH"),
        (["--gains", "0.5,-0.1,0.2"], "--gains must be TT,MID,HIGH"),
        (["--tt-control", "pid"], "--tt-control must be 'iir' or 'int'"),
        (["--mag", "16.5", "--tt-control", "iir"], "no IIR filter at 250 Hz"),
        (["--config", "missing.toml"], "run description not found"),
        (["--mag", "12", "--config", "x.toml"], "either --config or --mag"),
        (["--plot", "/dev/null/out"], "--plot must be a folder"),
        (["--misregistration", "0.3"], "--misregistration takes DX,DY[,ROT[,MAG]]"),
        (["--misregistration", "0.3,0,1,1,1"], "--misregistration takes DX,DY[,ROT[,MAG]]"),
        (["--misregistration", "3,0"], "--misregistration shift_x_pitch must be in -2..2 actuator pitches"),
        (["--misregistration", "0,nan"], "--misregistration shift_y_pitch must be in -2..2"),
        (["--misregistration", "0,0,12"], "--misregistration rotation_deg must be in -10..10 deg"),
        (["--misregistration", "0,0,0,x"], "--misregistration magnification must be a number in 0.8..1.2"),
        (["--ncpa", "-5"], "--ncpa must be in 0..1000 nm"),
        (["--ncpa", "nan"], "--ncpa must be"),
        (["--ncpa-offset-fraction", "1.5"], "--ncpa-offset-fraction must be in 0..1"),
        (["--ncpa-offset-fraction", "half"], "--ncpa-offset-fraction must be a number in 0..1"),
        (["--ideal", "--ncpa-offset-fraction", "0.3"], "--ideal turns OGTL and the error terms off"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args, message, capsys, cache_dir):
    status, out, err = run(["loop", "run", *args], capsys, cache_dir)
    assert status == 2
    assert message in err and err.count("\n") == 1 and out == ""


def test_gain_file_per_mode(tmp_path, capsys, cache_dir):
    gains = tmp_path / "gains.toml"
    gains.write_text("gains = [" + ", ".join(["0.3"] * 2 + ["0.25"] * 88) + "]\n")
    status, out, err = run([*FAINT, "--gains", str(gains), "--json"], capsys, cache_dir)
    assert status == 0, err
    assert json.loads(out)["configuration"]["gains"]["modes"][:3] == [0.3, 0.3, 0.25]
    short = tmp_path / "short.toml"
    short.write_text("gains = [0.3, 0.3, 0.2]\n")
    status, _, err = run([*FAINT, "--gains", str(short)], capsys, cache_dir)
    assert status == 2 and "3 gains but 90 modes" in err


@pytest.mark.slow
def test_the_default_pyramid_has_soul_s_field_of_view(capsys, cache_dir):
    """SOUL's 2.1" WFS field is the default (``defaults.WFS_FIELD_ARCSEC``): the run records it, and
    --wfs-field 0 (the sampled field, no stop) is another loop; out of range is one line."""
    base = ["loop", "run", "--mag", "16.5", "--duration", "0.1", "--json"]
    status, out, err = run(base, capsys, cache_dir)
    assert status == 0, err
    wide = json.loads(out)
    assert wide["configuration"]["field_of_view_arcsec"] == 2.1 and wide["configuration"]["oversampling"] == 2
    status, out, err = run([*base, "--wfs-field", "0"], capsys, cache_dir)
    assert status == 0, err
    sampled = json.loads(out)
    assert sampled["configuration"]["field_of_view_arcsec"] == 0.0 and sampled["metrics"] != wide["metrics"]
    status, out, err = run([*base, "--wfs-field", "4.5"], capsys, cache_dir)
    assert status == 2 and out == "" and err.strip().splitlines() == ["soulctl: error: --wfs-field must be in 0..4 arcsec, got 4.5"]
