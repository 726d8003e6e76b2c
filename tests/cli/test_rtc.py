"""`soulctl rtc check`: gain files and whole RTC descriptions, exit 0 / 3 / 2."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
from astropy.io import fits
from cli_run import run as _run

from soulctl.control.gains import LoopGains, mode_filters
from soulctl.control.rtc import build_rtc
from soulctl.observation import Observation

MAG = "13"  # the look-up table's R13 point: 980 Hz, 250 modes at binning 2


def _observation() -> Observation:
    from soulctl.cli.common import run_description

    return run_description(None, MAG, {}).observation


def _gains(obs, tt=0.5, mid=0.4, high=0.3) -> np.ndarray:
    return LoopGains(tt, mid, high).per_mode(obs.modes)


def test_gain_file_safe_and_unsafe(tmp_path, capsys):
    obs = _observation()
    safe, bad = tmp_path / "safe.toml", tmp_path / "bad.toml"
    safe.write_text("gains = [" + ", ".join(map(str, _gains(obs))) + "]\n")
    g = _gains(obs)
    g[40] = 5.0
    bad.write_text("gains = [" + ", ".join(map(str, g)) + "]\n")
    status, out, err = _run(["rtc", "check", str(safe), "--mag", MAG, "--json"], capsys)
    assert status == 0, err
    d = json.loads(out)
    assert d["passed"] and d["states"] == 2 * 8 + (obs.modes - 2) and len(d["modes"]) == obs.modes
    status, out, _ = _run(["rtc", "check", str(bad), "--mag", MAG, "--json"], capsys)
    assert status == 3
    assert json.loads(out)["failed_modes"] == [41]
    # a stricter modulus margin fails modes the default passes
    status, out, _ = _run(["rtc", "check", str(safe), "--mag", MAG, "--modulus-margin", "0.99", "--json"], capsys)
    assert status == 3 and json.loads(out)["failed_modes"]


def test_bad_input_is_exit_2(tmp_path, capsys):
    short = tmp_path / "short.toml"
    short.write_text("gains = [0.5, 0.5, 0.3]\n")
    status, _, err = _run(["rtc", "check", str(short), "--mag", MAG], capsys)
    assert status == 2 and "controls 250 modes" in err
    status, _, err = _run(["rtc", "check", str(tmp_path / "none.toml"), "--mag", MAG], capsys)
    assert status == 2 and "not found" in err
    status, _, err = _run(["rtc", "check", str(short), "--mag", MAG, "--modulus-margin", "2"], capsys)
    assert status == 2
    status, _, err = _run(["rtc", "check", str(short), "--mag", MAG, "--wfs-field", "4.5"], capsys)
    assert status == 2 and "--wfs-field must be in 0..4" in err


def _description(obs, forgetting=0.99):
    rng = np.random.default_rng(1)
    R, M = rng.standard_normal((obs.modes, 64)), rng.standard_normal((672, obs.modes))
    filters = mode_filters(obs, LoopGains(0.5, 0.4, 0.3, forgetting), obs.modes)
    m = build_rtc(filters, R, M)
    return {"Lambda": m.Lambda, "Delta": m.Delta, "Xi": m.Xi, "Sigma": m.Sigma, "R": R, "M": M}


def _write(path, arrays):
    if path.suffix == ".npz":
        np.savez(path, **arrays)
    elif path.suffix == ".h5":
        with h5py.File(path, "w") as f:
            for k, v in arrays.items():
                f[k] = v
    else:
        fits.HDUList([fits.PrimaryHDU()] + [fits.ImageHDU(v, name=k.upper()) for k, v in arrays.items()]).writeto(path)


@pytest.mark.parametrize("suffix", [".npz", ".h5", ".fits"])
def test_rtc_description_rebuilt_and_compared(tmp_path, capsys, suffix):
    obs = _observation()
    good, wrong = tmp_path / f"rtc{suffix}", tmp_path / f"wrong{suffix}"
    _write(good, _description(obs))
    _write(wrong, _description(obs, forgetting=0.98))  # not the declared leaky integrators
    status, out, err = _run(["rtc", "check", str(good), "--mag", MAG, "--json"], capsys)
    assert status == 0, err
    d = json.loads(out)
    assert all(v < 1e-12 for v in d["rebuild_differences"].values())
    assert [m["gain"] for m in d["modes"][:3]] == pytest.approx([0.5, 0.5, 0.4])
    status, out, _ = _run(["rtc", "check", str(wrong), "--mag", MAG, "--json"], capsys)
    assert status == 3
    diffs = json.loads(out)["rebuild_differences"]
    assert diffs["Lambda"] > 1e-3 and diffs["Xi"] < 1e-12


def test_rtc_description_missing_matrix_is_exit_2(tmp_path, capsys):
    arrays = _description(_observation())
    del arrays["Sigma"]
    path = tmp_path / "rtc.npz"
    _write(path, arrays)
    status, _, err = _run(["rtc", "check", str(path), "--mag", MAG], capsys)
    assert status == 2 and "missing Sigma" in err


@pytest.mark.slow
@pytest.mark.parametrize("noise", [{}, {"calibration.photons_per_frame": 50.0}], ids=["noiseless", "calibration noise"])
def test_misregistration_verdict_before_an_upload_is_loop_runs(noise, tmp_path, capsys, cache_dir):
    """`rtc check --misregistration` judges the coupled loop of the moved mirror as `loop run`
    does at the end of a run: with the run's optical gains as the chi table and the same
    reconstructor (the measured one when the description has calibration noise), the same
    verdict (noiseless: two pitches of shift lose the default R16.5 gains, exit 3; half a pitch
    does not); the [misregistration] of --config is read as the option is."""
    from soulctl.cli.common import run_description
    from soulctl.loop.chi_model import optical_gain_table
    from soulctl.loop.run import calibration_for
    from soulctl.optics.cache import ArrayCache

    description = run_description(None, "16.5", {"run.oversampling": 1, "run.wfs_field_arcsec": 0.0, **noise})
    config, gains, table = tmp_path / "run.toml", tmp_path / "gains.toml", tmp_path / "chi.csv"
    config.write_text(description.to_toml())
    resolved = description.resolved()
    g = LoopGains(*resolved.controller.gains).per_mode(description.observation.modes)
    gains.write_text("gains = [" + ", ".join(map(repr, g.tolist())) + "]\n")
    request = description.request()
    gamma = optical_gain_table(calibration_for(request, ArrayCache(cache_dir)), ArrayCache(cache_dir), request.seeing_arcsec)
    table.write_text("mode,optical_gain\n" + "".join(f"{i + 1},{x!r}\n" for i, x in enumerate(gamma.tolist())))
    check = ["rtc", "check", str(gains), "--config", str(config), "--chi-table", str(table), "--cache-dir", str(cache_dir)]
    run = ["loop", "run", "--config", str(config), "--duration", "0.3", "--no-ogtl", "--cache-dir", str(cache_dir), "--json"]
    statuses, poles = [], []
    for shift in ("2,0", "0.5,0"):
        status, out, err = _run([*check, "--json", "--misregistration", shift], capsys)
        assert status in (0, 3) and "Traceback" not in err, err
        verdict = json.loads(out)["misregistration_stability"]
        assert json.loads(out)["passed"] is verdict["passed"] is (status == 0)
        run_status, out, err = _run([*run, "--misregistration", shift], capsys)
        assert run_status == status, err
        in_run = json.loads(out)["misregistration_stability"]
        assert verdict["unstable"] == in_run["unstable"] and verdict["eigenmodes"] == in_run["eigenmodes"]
        for key in ("largest_pole", "margin", "largest_phase_deg"):
            assert verdict[key] == pytest.approx(in_run[key], rel=1e-9), key
        statuses.append(status)
        poles.append(verdict["largest_pole"])
    if not noise:
        assert statuses == [3, 0]
        status, out, err = _run([*check, "--json", "--misregistration", "0,0"], capsys)  # registered: the per-mode checks only
        assert status == 0 and json.loads(out)["misregistration_stability"] is None
        status, out, err = _run([*check, "--json", "--misregistration", "0.5,0", "--wfs-field", "2.1"], capsys)
        assert status in (0, 3), err  # --wfs-field over the description's field: another pyramid, another R D'
        assert json.loads(out)["misregistration_stability"]["largest_pole"] != pytest.approx(poles[1], rel=1e-6)
        moved = tmp_path / "moved.toml"
        moved.write_text(description.with_values({"misregistration.shift_x_pitch": 2.0}).to_toml())
        status, out, err = _run([*check[:4], str(moved), *check[5:]], capsys)
        assert status == 3 and "mis-registration: unstable eigenmodes" in out and "NOT safe" in out


@pytest.mark.slow
def test_a_coupled_gain_margin_below_the_criterion_is_named(tmp_path, capsys, cache_dir):
    """A moved loop that is stable but with less common gain margin than --gain-margin fails
    the check, and the verdict says why (the per-mode margins all pass)."""
    gains = tmp_path / "gains.toml"
    gains.write_text("gains = [" + ", ".join(["0.3"] * 90) + "]\n")
    args = ["rtc", "check", str(gains), "--mag", "16.5", "--misregistration", "0.2,0", "--cache-dir", str(cache_dir)]
    status, out, err = _run([*args, "--json"], capsys)
    d = json.loads(out)
    margin = d["misregistration_stability"]["margin"]
    assert status == 0 and d["misregistration_stability"]["stable"] and 1 < margin < min(m["gain_margin"] for m in d["modes"])
    status, out, err = _run([*args, "--json", "--gain-margin", f"{margin * 1.01:.6g}"], capsys)
    d = json.loads(out)
    assert status == 3 and d["failed_modes"] == [] and d["misregistration_stability"]["passed"] is False
    status, out, err = _run([*args, "--gain-margin", f"{margin * 1.01:.6g}"], capsys)
    assert status == 3 and "below --gain-margin" in " ".join(out.split())


def test_misregistration_option_refused_with_one_line(tmp_path, capsys):
    gains = tmp_path / "gains.toml"
    gains.write_text("gains = [" + ", ".join(map(str, _gains(_observation()))) + "]\n")
    for value, message in (("0.1", "--misregistration takes DX,DY"), ("0.1,9", "--misregistration shift_y_pitch must be in")):
        status, out, err = _run(["rtc", "check", str(gains), "--mag", MAG, "--misregistration", value], capsys)
        assert status == 2 and message in err and err.count("\n") == 1 and out == "", err
