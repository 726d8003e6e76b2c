"""examples/ci/check_params.sh, the README's chain, on a small simulated night: identify ->
design -> offline MGM -> rtc check, exit 0 with every artefact written."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "examples" / "ci" / "check_params.sh"


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("soulctl") is None, reason="needs the installed soulctl command")
def test_ci_chain_on_a_simulated_night(tmp_path):
    def run(*args):
        return subprocess.run(args, cwd=tmp_path, capture_output=True, text=True, timeout=600)

    config = run("soulctl", "loop", "run", "--mag", "16.5", "--print-config")
    assert config.returncode == 0, config.stderr
    (tmp_path / "night.toml").write_text(config.stdout)
    night = run("soulctl", "loop", "run", "--config", "night.toml", "--duration", "3", "--telemetry", "night.h5")
    assert night.returncode == 0, night.stderr
    r = run("sh", str(SCRIPT), "night.h5", "night.toml", "out")
    assert r.returncode == 0, r.stderr
    out = tmp_path / "out"
    for name in ("plant.toml", "roots.csv", "gains.toml", "identify.json", "design.json", "gains.json", "check.json"):
        assert (out / name).is_file(), name
    check = json.loads((out / "check.json").read_text())
    identify = json.loads((out / "identify.json").read_text())
    assert check["passed"] and check["delay_frames"] == pytest.approx(identify["delay_frames"]["value"])
    assert abs(identify["delay_frames"]["value"] - identify["delay_frames"]["recorded"]) < 0.1
    # 3 s at 8 m/s: the seeing (1.0") within 10 %, L0 not estimated (~6 correlation times of modes 3-14)
    assert abs(identify["turbulence"]["seeing_arcsec"] - 1.0) < 0.1 and "correlation times" in identify["not_estimated"]["L0"]
    # an unsafe gain file fails the job with exit 3
    (out / "gains.toml").write_text("gains = [" + ", ".join(["9.0"] * len(check["modes"])) + "]\n")
    bad = run("soulctl", "rtc", "check", "out/gains.toml", "--config", "night.toml", "--plant", "out/plant.toml")
    assert bad.returncode == 3, bad.stderr
