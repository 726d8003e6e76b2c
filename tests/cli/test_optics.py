"""`soulctl optics atmosphere|calibrate|gains`: output, cache, exit status and one-line errors."""

import json

import numpy as np
import pytest
from cheap import CHEAP_PYRAMID
from cli_run import run

from soulctl.optics.atmosphere import tilt_variance_rad2
from soulctl.run_config import RunConfig

SMALL = ["--binning", "4", "--modes", "20", *CHEAP_PYRAMID]


def test_atmosphere_json_against_the_seeing_relations(capsys):
    status, out, err = run(["optics", "atmosphere", "--seeing", "1.0", "--wind", "10", "--json"], capsys)
    assert status == 0 and err == ""
    d = json.loads(out)
    assert d["r0_500nm_m"] == pytest.approx(0.98 * 500e-9 / (1.0 / 206265), rel=1e-3)
    assert d["r0_750nm_m"] / d["r0_500nm_m"] == pytest.approx(1.5**1.2)
    assert d["effective_wind_m_s"] == pytest.approx(10.0)
    assert d["tau0_500nm_ms"] == pytest.approx(0.314 * d["r0_500nm_m"] / 10.0 * 1e3)
    assert sum(layer["weight"] for layer in d["layers"]) == pytest.approx(1.0)
    # the Tip/Tilt of the temporal-PSD model's spatial integral against the Bessel integral
    a2 = tilt_variance_rad2(8.222, d["r0_500nm_m"], 25.0)  # Zernike coefficient, rad^2 at 500 nm
    expected_mas = np.sqrt(a2) * 500e-9 / (2 * np.pi) * 4 / 8.222 * 206264806.2
    assert d["tilt_rms_per_axis_mas"] == pytest.approx(expected_mas, rel=0.02)


@pytest.mark.slow
def test_calibrate_uses_and_fills_the_cache(tmp_path, capsys):
    args = ["optics", "calibrate", *SMALL, "--cache-dir", str(tmp_path), "--json"]
    status, out, _ = run(args, capsys)
    first = json.loads(out)
    assert status == 0 and first["from_cache"] is False
    assert first["subapertures_across"] == 10 and first["modes"] == 20 and first["slopes"] == 2 * first["valid_subapertures"]
    status, out, _ = run(args, capsys)
    assert json.loads(out)["from_cache"] is True
    status, out, _ = run([*args, "--no-cache"], capsys)
    assert json.loads(out)["from_cache"] is False and json.loads(out)["cache_file"] is None


def test_calibrate_from_the_look_up_table(cache_dir, capsys):
    status, out, _ = run(["optics", "calibrate", "--mag", "16", *CHEAP_PYRAMID, "--cache-dir", str(cache_dir)], capsys)
    assert status == 0
    assert "3 / 13" in out and "90" in out and "condition number" in out


def test_gains_table_csv_and_json(tmp_path, cache_dir, capsys):
    csv = tmp_path / "og.csv"
    args = ["optics", "gains", "--seeing", "0.8", *SMALL, "--screens", "1", "--cache-dir", str(cache_dir)]
    status, out, _ = run([*args, "--out", str(csv)], capsys)
    assert status == 0 and "Optical gains" in out and "1..2" in out
    assert csv.read_text().count("\n") == 5 + 20 and "# oversampling = 1, wfs_field_arcsec = 0.0\n" in csv.read_text()
    status, out, _ = run([*args, "--json"], capsys)
    d = json.loads(out)
    assert len(d["optical_gains"]) == 20 and d["level"]["seeing_arcsec"] == 0.8
    assert (d["oversampling"], d["wfs_field_arcsec"]) == (1, 0.0)  # the sensor the table belongs to
    assert np.all(np.array(d["optical_gains"]) <= 1.0)
    status, out, _ = run([*args, "--json", "--seed", "2"], capsys)
    assert json.loads(out)["optical_gains"] != d["optical_gains"]  # the seed matters
    status, out, _ = run([*args, "--json"], capsys)
    assert json.loads(out)["optical_gains"] == d["optical_gains"]  # and repeats


@pytest.mark.parametrize(
    "args, message",
    [
        (["optics", "atmosphere", "--seeing", "0"], "seeing must be in 0.05..10"),
        (["optics", "atmosphere", "--seeing", "-1"], "seeing must be in 0.05..10"),
        (["optics", "atmosphere", "--L0", "0"], "--L0 must be in 0.5..10000 m, got 0"),
        (["optics", "atmosphere", "--wind", "-2"], "--wind must be in 0..100"),
        (["optics", "calibrate", "--binning", "5"], "--binning must be one of 1, 2, 3, 4"),
        (["optics", "calibrate", "--binning", "4", "--modulation", "-1"], "--modulation must be in 0..20"),
        (
            ["optics", "calibrate", "--binning", "4", "--modes", "700", *CHEAP_PYRAMID],
            "--modes must be in 2..671, got 700",
        ),
        (["optics", "calibrate", "--binning", "4", "--oversampling", "9"], "--oversampling must be in 1..4, got 9"),
        (["optics", "calibrate", "--mag", "12", "--config", "x.toml"], "either --config or --mag"),
        (["optics", "gains", "--seeing", "0"], "seeing must be in 0.05..10"),
        (["optics", "gains", "--L0", "-5"], "--L0 must be in 0.5..10000 m, got -5"),
        (["optics", "gains", "--screens", "0", *SMALL], "--screens must be in 1..64, got 0"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args, message, capsys, cache_dir):
    status, out, err = run([*args, "--cache-dir", str(cache_dir)] if args[1] != "atmosphere" else args, capsys)
    assert status == 2
    assert message in err and err.count("\n") == 1 and out == ""


def test_gains_writes_nothing_on_bad_input(tmp_path, capsys):
    csv = tmp_path / "og.csv"
    status, _, _ = run(["optics", "gains", "--seeing", "-1", *SMALL, "--out", str(csv)], capsys)
    assert status == 2 and not csv.exists()


def test_the_field_of_view_of_option_description_and_default(tmp_path, capsys, cache_dir):
    """optics calibrate reads with the runs' pyramid: SOUL's 2.1" field by default (a stop of
    55.8 lambda/D, a 120-pixel sensing pupil at o = 1: 3x), --config's [run] wfs_field_arcsec
    when it has one, --wfs-field over both."""
    base = ["optics", "calibrate", "--binning", "4", "--modes", "20", "--cache-dir", str(cache_dir), "--json"]
    status, out, err = run([*base, "--oversampling", "1"], capsys)
    assert status == 0, err
    d = json.loads(out)
    assert d["wfs_field_arcsec"] == 2.1 and d["field_stop_lambda_over_d"] == pytest.approx(55.8, abs=0.05)
    assert (d["pupil_pixels"], d["sensing_pupil_pixels"], d["fft_size"]) == (40, 120, 288)
    description = tmp_path / "run.toml"
    values = {"star.magnitude_r": 16.5, "run.wfs_field_arcsec": 0.0, "run.oversampling": 1}
    description.write_text(RunConfig().with_values(values).to_toml())
    status, out, err = run([*base, "--config", str(description)], capsys)
    assert status == 0, err
    d = json.loads(out)
    assert d["wfs_field_arcsec"] == 0.0 and d["sensing_pupil_pixels"] == d["pupil_pixels"] == 40 and d["fft_size"] == 96
    status, out, err = run([*base, "--config", str(description), "--wfs-field", "1.5"], capsys)
    assert status == 0 and json.loads(out)["wfs_field_arcsec"] == 1.5


@pytest.mark.slow
def test_a_description_gives_the_whole_pyramid_and_mirror_it_runs(tmp_path, capsys, cache_dir):
    """--config gives the calibration `loop run --config` makes (its oversampling, field and
    influence functions, not only its star): the same cache key, the same interaction matrix;
    --oversampling overrides the description's."""
    from soulctl.loop.run import calibration_setup
    from soulctl.optics.cache import ArrayCache
    from soulctl.optics.calibration import calibrate

    description = RunConfig().with_values(
        {"star.magnitude_r": 17.0, "run.wfs_field_arcsec": 0.0, "run.oversampling": 1, "mirror.influence": "gaussian"}
    )
    path = tmp_path / "run.toml"
    path.write_text(description.to_toml())
    status, out, err = run(["optics", "calibrate", "--config", str(path), "--cache-dir", str(cache_dir), "--json"], capsys)
    assert status == 0, err
    d = json.loads(out)
    assert (d["oversampling"], d["influence"], d["modes"], d["binning"]) == (1, "gaussian", 54, 4)
    setup = calibration_setup(description.request())
    assert d["cache_file"] == str(ArrayCache(cache_dir).path(setup.key()))
    assert d["condition_number"] == pytest.approx(calibrate(setup, ArrayCache(cache_dir)).condition_number, rel=1e-12)
    status, out, err = run(
        ["optics", "calibrate", "--config", str(path), "--oversampling", "2", "--cache-dir", str(cache_dir), "--json"], capsys
    )
    assert status == 0 and json.loads(out)["oversampling"] == 2 and json.loads(out)["influence"] == "gaussian"
