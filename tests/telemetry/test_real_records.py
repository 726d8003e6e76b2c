"""Every telemetry command on each public record of a real AO system (tests/data/real, its
README gives each source, licence and what is known of the system), against the figures
known independently of soulctl."""

import importlib.util
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from cli_run import run

from soulctl.telemetry.formats import read_record

REAL = Path(__file__).resolve().parents[1] / "data" / "real"
MAS_PER_ARCSEC = 1000.0


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    spec = importlib.util.spec_from_file_location("make_aot", REAL / "make_aot.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.write_all(tmp_path_factory.mktemp("real"))


def test_the_corpus_is_small_and_licensed():
    sizes = sum(p.stat().st_size for p in REAL.rglob("*") if p.is_file())
    assert sizes < 5 * 2**20
    for name in ("keck_strap_n0088", "arte_downtiptilt"):
        assert "MIT License" in (REAL / name / "LICENSE").read_text() and name in (REAL / "README.md").read_text()


def test_keck_strap_loop(records, tmp_path, capsys):
    """The Keck II quad-cell loop: what the record states, its residual jitter (the centroids'
    RMS, computed here), its 19.9 Hz line, its delay and chi, MGM with its own controller."""
    path = records["keck_strap_n0088"]
    status, out, err = run(["telemetry", "inspect", path, "--json"], capsys)
    d = json.loads(out)
    assert status == 0 and (d["frames"], d["rate_hz"], d["modes"]) == (35806, 1000.0, 2), err
    assert (d["sensor"], d["corrector"], d["telescope"], d["telescope_diameter_m"]) == ("quad-cell", "tip-tilt-mirror", "Keck II", 10.0)
    arrays, _ = read_record(path)
    np.testing.assert_allclose(arrays["controller_den"], [[1.0, -0.6, -0.32, -0.08]] * 2, atol=1e-7)
    np.testing.assert_allclose(arrays["gains"], 0.1, rtol=1e-7)
    centroids = np.load(REAL / "keck_strap_n0088" / "Centroid_n0088.npy").astype(float)
    jitter = np.sqrt(np.mean(centroids.var(axis=0))) * MAS_PER_ARCSEC  # 48.9 mas per axis
    status, out, err = run(["telemetry", "psd", path, "--json"], capsys)
    tt = json.loads(out)["tt_jitter"]["measured_modes"]
    assert status == 0 and err == "" and tt["all"] == pytest.approx(jitter, rel=0.02)
    assert 0.8 * tt["above_3hz"] < tt["above_3hz_noise_floor"] < tt["above_3hz"]  # mostly measurement noise
    status, out, err = run(["telemetry", "identify", path, "--json"], capsys)
    ident = json.loads(out)
    assert status == 0, err
    assert ident["delay_frames"]["value"] == pytest.approx(2.5, abs=0.2) and ident["optical_gains"][0]["chi"] == pytest.approx(1.0, abs=0.3)
    assert [x["frequency_hz"]["value"] for x in ident["vibration_lines"]][:1] == pytest.approx([19.9], abs=0.1)
    delay = f"{ident['delay_frames']['value']:.2f}"
    assert run(["telemetry", "psd", path, "--pseudo-open-loop", "--delay-frames", delay], capsys)[0] == 0
    status, out, err = run(["optimize", "gains", "--telemetry", path, "--delay-frames", delay, "--json"], capsys)
    mgm = json.loads(out)
    assert status == 0 and mgm["chi"] == [1.0, 1.0] and len(mgm["reasons"]) == 2, err
    assert mgm["notes"] == ["structural resonance: none (the record's corrector: tip-tilt-mirror)"]  # on today's main LBT's 127 Hz
    for target in (tmp_path / "keck.h5", tmp_path / "Data_20170101_000000"):
        assert run(["telemetry", "convert", path, target], capsys)[0] == 0
        back, _ = read_record(target)
        np.testing.assert_array_equal(back["command_modes"], arrays["command_modes"].astype(np.float32))


def test_arte_snapshot(records, tmp_path, capsys):
    """100 frames: the rate from the time stamps, said so; spectra with warnings; nothing to
    identify and too short for MGM, each exit 2 with the reason."""
    path = records["arte_downtiptilt"]
    stamps = np.load(REAL / "arte_downtiptilt" / "downtiptilt.npz")["rawtimestamp"] * 1e-9
    status, out, err = run(["telemetry", "inspect", path, "--json"], capsys)
    d = json.loads(out)
    assert status == 0 and d["frames"] == 100 and d["rate_hz"] == pytest.approx(99 / (stamps[-1] - stamps[0]), rel=1e-5), err
    assert any(n["field"] == "rate_hz" and "time stamps" in n["note"] for n in d["notes"])
    np.testing.assert_allclose(read_record(path)[0]["gains"], 0.05, rtol=1e-7)
    status, out, err = run(["telemetry", "psd", path, "--json"], capsys)
    assert status == 0 and err.count("soulctl: warning:") == 2
    status, _, err = run(["telemetry", "identify", path], capsys)
    assert status == 2 and "nothing can be identified from 100 frames" in err and err.count("\n") == 1
    status, _, err = run(["optimize", "gains", "--telemetry", path, "--delay-frames", "2"], capsys)
    assert status == 2 and "must be at least" in err and err.count("\n") == 1
    for target in (tmp_path / "arte.h5", tmp_path / "Data_20240404_024500"):
        assert run(["telemetry", "convert", path, target], capsys)[0] == 0


GUIDE = REAL.parents[2] / "docs" / "guide.md"


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("soulctl") is None, reason="needs the installed soulctl command")
def test_the_guides_example_runs_as_written(tmp_path):
    """The lines of the guide's "soulctl on another AO system's records", run as written in a
    folder where tests/ is the repository's: each exits 0."""
    text = GUIDE.read_text()
    block = text[text.index("<!-- real-record-example") :].split("```sh\n", 1)[1].split("```", 1)[0]
    (tmp_path / "tests").symlink_to(REAL.parents[1])
    for line in block.strip().splitlines():
        command = line.split("  #")[0].strip()
        r = subprocess.run(command, shell=True, cwd=tmp_path, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, (command, r.stderr)
    assert (tmp_path / "records" / "keck_strap_n0088.fits").is_file()
