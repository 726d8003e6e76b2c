"""The formats: soulctl HDF5, AOT FITS (through aotpy) and LBT tracking-number folders.  Round
trips keep every field; aotpy reads soulctl's AOT files; soulctl reads AOT files built with
aotpy's own objects and LBT folders written with astropy from the documented layout; offline
MGM gives the same gains from the same run in each format; `soulctl telemetry` on each."""

import dataclasses
import datetime
import json

import aotpy
import numpy as np
import pytest
from astropy.io import fits
from cheap import CHEAP_PYRAMID
from cli_run import run

from soulctl.cli.app import main
from soulctl.observation import observation_for_magnitude
from soulctl.offline.mgm import recorded_run
from soulctl.telemetry.formats import open_telemetry, read_record, write_record

# test_offline_mgm's small loop: 54 modes at 407 Hz on a 40-px pupil, with an R11 star's flux
OBS = dataclasses.replace(observation_for_magnitude(17), magnitude_r=11.0)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory, optics_cache):
    """One run with every field and OGTL's and MGM's records, in the three formats."""
    root = tmp_path_factory.mktemp("formats")
    config = root / "small.toml"
    OBS.write_toml(config)
    h5 = root / "loop.h5"
    argv = ["loop", "run", "--config", config, *CHEAP_PYRAMID, "--seeing", "0.6", "--duration", "1.2", "--json"]
    argv += ["--telemetry", h5, "--telemetry-fields", "all", "--cache-dir", optics_cache.directory]
    assert main([str(a) for a in argv]) == 0
    fits_path, folder = root / "loop.fits", root / "Data_20261126_120000"
    assert main(["telemetry", "convert", str(h5), str(fits_path)]) == 0
    assert main(["telemetry", "convert", str(fits_path), str(folder)]) == 0
    back = root / "back.h5"
    assert main(["telemetry", "convert", str(folder), str(back)]) == 0
    return {"root": root, "config": config, "h5": h5, "fits": fits_path, "lbt": folder, "back": back, "cache": optics_cache.directory}


def test_round_trips_keep_every_field(recorded):
    a, at = read_record(recorded["h5"])
    for path in (recorded["fits"], recorded["lbt"], recorded["back"]):
        b, bt = read_record(path)
        assert set(b) == set(a), path
        for name in a:
            np.testing.assert_array_equal(b[name], a[name], err_msg=f"{path}: {name}")
        assert bt == at, path
    assert {"slopes", "commands", "gain_history/gains", "reconstructor", "modes_to_commands"} <= set(a)


def test_aotpy_reads_soulctls_aot_file(recorded):
    a, at = read_record(recorded["h5"])
    system = aotpy.AOSystem.read_from_file(str(recorded["fits"]))
    loop = system.loops[0]
    assert isinstance(loop.input_sensor, aotpy.Pyramid) and loop.input_sensor.n_sides == 4
    assert loop.framerate == pytest.approx(at["rate_hz"]) and loop.delay == pytest.approx(at["delay_frames"])
    assert loop.input_sensor.modulation == pytest.approx(OBS.modulation_lambda_over_d * 750e-9)
    frames = len(a["frame_counter"])
    np.testing.assert_allclose(np.asarray(loop.input_sensor.measurements.data).reshape(frames, -1), a["slopes"], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(loop.commands.data) * 1e9, a["commands"], rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(np.asarray(loop.modal_coefficients.data), a["command_modes"], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(loop.time_filter_num.data)[:, 0], a["gains"], rtol=1e-6)
    np.testing.assert_array_equal(loop.time.frame_numbers, a["frame_counter"])


def _offline(path, recorded, capsys, *extra):
    return run(["optimize", "gains", "--method", "mgm", "--telemetry", path, "--json", "--cache-dir", recorded["cache"], *extra], capsys)


def test_offline_mgm_gives_the_same_gains_in_every_format(recorded, capsys):
    gains = {}
    for kind in ("h5", "fits", "lbt"):
        status, out, err = _offline(recorded[kind], recorded, capsys)
        assert status == 0, err
        gains[kind] = json.loads(out)["gains"]
    assert gains["fits"] == gains["h5"] and gains["lbt"] == gains["h5"]


# ------------------------------------------------------------- AOT files built with aotpy


def _aot_system(kind: str, frames: int = 600, commands: bool = True, seed: int = 2):
    """An SCAO system built with aotpy's objects alone, with OBS's modes, rate and delay: a
    random-walk disturbance measured through a known reconstructor (units as the standard)."""
    rng = np.random.default_rng(seed)
    n_modes, n_sub, n_act = OBS.modes, 100, 120
    r = rng.normal(size=(n_modes, 2 * n_sub))
    m2c = rng.normal(size=(n_act, n_modes))
    modes = np.cumsum(rng.normal(size=(frames, n_modes)), axis=0) * 5.0
    slopes = modes @ np.linalg.pinv(r).T
    system = aotpy.AOSystem(ao_mode="SCAO", date_beginning=datetime.datetime(2026, 11, 26, tzinfo=datetime.UTC))
    system.main_telescope = aotpy.MainTelescope(uid="TEL", enclosing_diameter=8.0)
    t = aotpy.Time(uid="T", frame_numbers=list(range(frames)))
    star = aotpy.NaturalGuideStar("NGS")
    meas = aotpy.Image("SLOPES", slopes.reshape(frames, 2, n_sub).astype(np.float32), time=t)
    if kind == "pyramid":
        wfs = aotpy.Pyramid(uid="WFS", source=star, n_valid_subapertures=n_sub, n_sides=4, dimensions=2, measurements=meas)
    else:
        wfs = aotpy.ShackHartmann(uid="WFS", source=star, n_valid_subapertures=n_sub, subaperture_size=8.0, measurements=meas)
    dm = aotpy.DeformableMirror(uid="DM", telescope=system.main_telescope, n_valid_actuators=n_act)
    loop = aotpy.ControlLoop(uid="LOOP", input_sensor=wfs, commanded_corrector=dm, time=t, framerate=OBS.frame_rate_hz)
    loop.delay = OBS.delay_frames
    loop.measurements_to_modes = aotpy.Image("S2M", r.reshape(n_modes, 2, n_sub).astype(np.float32))
    loop.modes_to_commands = aotpy.Image("M2C", m2c.astype(np.float32))
    loop.time_filter_num = aotpy.Image("NUM", np.full((n_modes, 1), 0.3, dtype=np.float32))
    if commands:
        loop.commands = aotpy.Image("CMD", (modes @ m2c.T * 1e-9).astype(np.float32), unit="m", time=t)
    system.sources, system.wavefront_sensors, system.wavefront_correctors, system.loops = [star], [wfs], [dm], [loop]
    return system, {"slopes": slopes, "r": r, "m2c": m2c, "modes": modes}


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["pyramid", "shack-hartmann"])
def test_soulctl_reads_aot_files_built_with_aotpy(kind, tmp_path, capsys, recorded):
    system, truth = _aot_system(kind)
    path = tmp_path / "foreign.fits"
    system.write_to_file(str(path))
    with open_telemetry(path) as tm:
        assert tm.attribute("rate_hz") == OBS.frame_rate_hz and tm.dim("n_modes") == OBS.modes
        np.testing.assert_allclose(tm.read("slopes"), truth["slopes"], rtol=1e-5, atol=1e-9)
        np.testing.assert_allclose(tm.read("measured_modes"), truth["slopes"] @ truth["r"].T, rtol=1e-3, atol=1e-3)
        np.testing.assert_allclose(tm.read("command_modes"), truth["modes"], rtol=1e-3, atol=1e-2)
        np.testing.assert_allclose(tm.read("gains"), 0.3, rtol=1e-6)
    status, out, err = run(["telemetry", "inspect", path, "--json"], capsys)
    assert status == 0 and json.loads(out)["format"] == "aot" and json.loads(out)["frames"] == 600, err
    status, out, err = run(["telemetry", "psd", path, "--modes", "1,2,5", "--pseudo-open-loop", "--json"], capsys)
    assert status == 0, err
    assert set(json.loads(out)["psd_nm2_per_hz"]) == {"measured_modes", "command_modes", "pseudo_open_loop"}
    # offline MGM on a foreign record: the observation from --config (modes, rate and delay agree),
    # the pyramid SOUL's 2.1" field (a soulctl record without the field ran the sampled one, 0)
    with open_telemetry(path) as tm:
        assert recorded_run(tm, OBS, path).wfs_field_arcsec == 2.1
    status, out, err = _offline(path, recorded, capsys, "--config", recorded["config"])
    assert status == 0 and len(json.loads(out)["gains"]) == OBS.modes, err


def test_an_aot_file_without_commands_is_refused_where_an_analysis_needs_them(tmp_path, capsys):
    system, _ = _aot_system("pyramid", commands=False)
    path = tmp_path / "nocmd.fits"
    system.write_to_file(str(path))
    config = tmp_path / "small.toml"
    OBS.write_toml(config)
    status, _, err = run(["optimize", "gains", "--method", "mgm", "--telemetry", path, "--config", config], capsys)
    assert status == 2 and "lacks command_modes" in err and err.count("\n") == 1
    status, _, err = run(["telemetry", "psd", path, "--pseudo-open-loop"], capsys)
    assert status == 2 and "lacks command_modes" in err
    assert run(["telemetry", "psd", path], capsys)[0] == 0  # the measured modes alone


# ------------------------------------------------ LBT folders written from the documented layout


def _lbt_folder(root, tn="20261126_101010", frames=400, counter=None, modes_frames=None):
    """A TN folder written with astropy from docs/telemetry-formats.md (not soulctl's writer):
    interleaved slopes, integrated modes and commands in m of surface, the loop rate as
    ocam2.FRAMERATE in wfs.fits."""
    rng = np.random.default_rng(3)
    folder = root / f"Data_{tn}"
    folder.mkdir()
    counter = np.arange(frames) if counter is None else counter
    fits.PrimaryHDU(counter.astype(np.int32)).writeto(folder / f"FramesCounter_{tn}.fits")
    sx, sy = rng.normal(size=(frames, 50)), rng.normal(size=(frames, 50))
    interleaved = np.empty((frames, 100))
    interleaved[:, 0::2], interleaved[:, 1::2] = sx, sy
    fits.PrimaryHDU(interleaved.astype(np.float32)).writeto(folder / f"Slopes_{tn}.fits")
    modes = rng.normal(size=(modes_frames or frames, 20)) * 1e-8  # m of surface
    fits.PrimaryHDU(modes.astype(np.float32)).writeto(folder / f"Modes_{tn}.fits")
    header = fits.Header()
    header["HIERARCH ocam2.FRAMERATE"] = 1700.0
    fits.PrimaryHDU(header=header).writeto(folder / "wfs.fits")
    return folder, {"sx": sx, "sy": sy, "modes": modes}


def test_soulctl_reads_an_lbt_folder_written_from_the_layout(tmp_path, capsys):
    folder, truth = _lbt_folder(tmp_path)
    with open_telemetry(folder, required=()) as tm:
        assert tm.attribute("rate_hz") == 1700.0
        np.testing.assert_allclose(tm.read("slopes"), np.hstack([truth["sx"], truth["sy"]]), rtol=1e-6)
        np.testing.assert_allclose(tm.read("command_modes"), truth["modes"] * 2e9, rtol=1e-6)  # nm of wavefront
    status, out, err = run(["telemetry", "inspect", folder, "--json"], capsys)
    d = json.loads(out)
    assert status == 0 and d["format"] == "lbt" and d["frames"] == 400 and d["duration_s"] == pytest.approx(400 / 1700), err


def test_decimation_and_gaps_are_flagged_never_misaligned(tmp_path, capsys):
    counter = np.arange(0, 800, 2)
    counter[200:] += 6  # three decimated samples lost after row 199
    folder, _ = _lbt_folder(tmp_path, counter=counter)
    status, out, _ = run(["telemetry", "inspect", folder, "--json"], capsys)
    d = json.loads(out)
    assert status == 0 and (d["decimation"], d["gaps"], d["lost_frames"]) == (1, 1, 3)
    with open_telemetry(folder, required=()) as tm:
        np.testing.assert_array_equal(tm.read("frame_counter"), counter)  # every row keeps its frame number
    status, _, err = run(["telemetry", "psd", folder], capsys)
    assert status == 2 and "decimated (1) or have gaps (1)" in err


def test_a_folder_whose_files_disagree_is_refused_naming_the_file(tmp_path, capsys):
    folder, _ = _lbt_folder(tmp_path, modes_frames=399)
    status, _, err = run(["telemetry", "inspect", folder], capsys)
    assert status == 2 and "Modes_20261126_101010.fits has 399 frames, FramesCounter_20261126_101010.fits has 400" in err
    (folder / "FramesCounter_20261126_101010.fits").unlink()
    status, _, err = run(["telemetry", "inspect", folder], capsys)
    assert status == 2 and "no FramesCounter_<TN>.fits" in err


def test_a_file_of_no_known_format_is_refused(tmp_path, capsys):
    bad = tmp_path / "notes.txt"
    bad.write_text("not telemetry")
    status, _, err = run(["telemetry", "inspect", bad], capsys)
    assert status == 2 and "is not an HDF5 file, an AOT FITS file (.fits) or an LBT tracking-number folder" in err
    bad_fits = tmp_path / "x.fits"
    bad_fits.write_text("SIMPLE = F")
    status, _, err = run(["telemetry", "inspect", bad_fits], capsys)
    assert status == 2 and "is not a readable AOT FITS file" in err and err.count("\n") == 1


def test_writing_a_record_refuses_an_existing_folder(tmp_path, recorded):
    a, at = read_record(recorded["h5"])
    (tmp_path / "Data_20261126_000000").mkdir()
    with pytest.raises(Exception, match="exists"):
        write_record(tmp_path / "Data_20261126_000000", a, at)


def test_loop_run_writes_each_format_by_its_name(tmp_path, capsys, optics_cache):
    small = [
        "loop",
        "run",
        "--mag",
        "16.5",
        *CHEAP_PYRAMID,
        "--duration",
        "0.3",
        "--cache-dir",
        optics_cache.directory,
    ]
    for target in (tmp_path / "run.fits", tmp_path / "Data_20261126_000001"):
        status, first, err = run([*small, "--telemetry", target, "--json"], capsys)
        assert status == 0, err
        status, out, err = run(["telemetry", "inspect", target, "--json"], capsys)
        d = json.loads(out)
        assert status == 0 and d["frames"] == 75 and d["status"] == "complete" and d["run_description"], err
        # the run again from its telemetry, whichever format: the same numbers
        status, again, err = run(["loop", "run", "--config", target, "--cache-dir", optics_cache.directory, "--json"], capsys)
        assert status == 0 and json.loads(again)["metrics"] == json.loads(first)["metrics"], err
    assert aotpy.AOSystem.read_from_file(str(tmp_path / "run.fits")).loops[0].framerate == 250.0
    assert (tmp_path / "Data_20261126_000001" / "FramesCounter_20261126_000001.fits").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["Data_20261126_000001", "run.fits"]  # no temporaries


def test_the_psd_integrates_to_the_variance_in_mas(recorded, capsys):
    """The cumulative Tip/Tilt jitter at the lowest frequency is the RMS per axis: checked
    against the records' variance and the tilt scale of the LBT pupil computed here."""
    status, out, err = run(["telemetry", "psd", recorded["h5"], "--modes", "1,2", "--json"], capsys)
    assert status == 0, err
    a, _ = read_record(recorded["h5"])
    x = np.linspace(-4.111, 4.111, 2001)
    xx, yy = np.meshgrid(x, x)
    r = np.hypot(xx, yy)
    inside = (r <= 4.111) & (r >= 0.111 * 4.111)
    nm_per_mas = np.sqrt(np.mean(xx[inside] ** 2)) * 1e9 / (180 / np.pi * 3600e3)
    expected = np.sqrt(a["measured_modes"][:, :2].astype(float).var(axis=0).mean()) / nm_per_mas
    assert json.loads(out)["tt_jitter_mas"]["measured_modes"] == pytest.approx(expected, rel=0.1)


def test_offline_mgm_takes_the_delay_and_optical_gains_from_options(recorded, capsys, tmp_path):
    """--delay-frames and --chi-table replace the record's delay and the model's optical gains:
    MGM's optimum moves with them; a table that misses a mode, or the options without a
    record, exit 2 naming the problem."""
    base = json.loads(_offline(recorded["h5"], recorded, capsys)[1])["optimum"]
    status, out, err = _offline(recorded["h5"], recorded, capsys, "--delay-frames", "2.5")
    assert status == 0 and json.loads(out)["optimum"] != base, err
    table = tmp_path / "og.csv"
    table.write_text("# flat optical gains\nmode,optical_gain,spread\n" + "".join(f"{m},0.5,0\n" for m in range(1, OBS.modes + 1)))
    status, out, err = _offline(recorded["h5"], recorded, capsys, "--chi-table", table)
    assert status == 0, err
    halved = json.loads(out)
    assert halved["chi"] == [0.5] * OBS.modes and halved["optimum"] != base
    table.write_text("mode,optical_gain\n" + "".join(f"{m},0.5\n" for m in range(1, OBS.modes)))
    status, _, err = _offline(recorded["h5"], recorded, capsys, "--chi-table", table)
    assert status == 2 and f"lacks mode {OBS.modes}" in err
    status, _, err = run(["optimize", "gains", "--mag", "16.5", "--delay-frames", "2"], capsys)
    assert status == 2 and "--delay-frames applies to offline MGM" in err


# ------------------------------------------- what adversarial testing found (each exited 1)


def _lbt_copy(recorded, tmp_path, tn, edit):
    import shutil

    folder = tmp_path / f"Data_{tn}"
    shutil.copytree(recorded["lbt"], folder)
    for p in folder.iterdir():
        p.rename(folder / p.name.replace("20261126_120000", tn))
    edit(folder, tn)
    return folder


def _header(folder, key, value):
    with fits.open(folder / "wfs.fits", mode="update") as h:
        h[0].header[key] = value


def _nan_counter(folder, tn):
    c = fits.getdata(folder / f"FramesCounter_{tn}.fits").astype(float)
    c[0] = np.nan
    fits.PrimaryHDU(c).writeto(folder / f"FramesCounter_{tn}.fits", overwrite=True)


def _odd_slopes(folder, tn):
    (folder / f"soulctl_{tn}.fits").unlink()
    for p in folder.glob("Rec_*.fits"):
        p.unlink()
    frames = len(fits.getdata(folder / f"FramesCounter_{tn}.fits"))
    fits.PrimaryHDU(np.zeros((frames, 5))).writeto(folder / f"Slopes_{tn}.fits", overwrite=True)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda f, tn: _header(f, "HIERARCH ocam2.FRAMERATE", "fast"), "keyword ocam2.FRAMERATE must be a number"),
        (lambda f, tn: _nan_counter(f, tn), "must hold whole frame numbers"),
        (_odd_slopes, "has 5 columns, expected x, y pairs"),
        (lambda f, tn: (f / f"soulctl_{tn}.fits").write_bytes(bytes(range(256)) * 20), "is not a readable soulctl record"),
    ],
)
def test_damaged_lbt_folders_exit_2_naming_the_file(recorded, tmp_path, capsys, edit, message):
    folder = _lbt_copy(recorded, tmp_path, "20261126_130000", edit)
    status, _, err = run(["telemetry", "inspect", folder], capsys)
    assert status == 2 and message in err and err.count("\n") == 1, err


def test_records_without_rate_or_delay_convert_and_odd_configurations_are_reported(recorded, tmp_path, capsys):
    """A real LBT folder holds no delay (and may hold no wfs.fits): it still converts to AOT;
    a configuration of other JSON types is left out of the report, not a crash; a file named
    Data_<...>.h5 is HDF5; a 1-frame record survives the LBT round trip."""

    def bare(folder, tn):
        (folder / "wfs.fits").unlink()
        (folder / f"soulctl_{tn}.fits").unlink()

    folder = _lbt_copy(recorded, tmp_path, "20261126_140000", bare)
    assert run(["telemetry", "convert", folder, tmp_path / "bare.fits"], capsys)[0] == 0
    with open_telemetry(tmp_path / "bare.fits", required=()) as tm:
        assert not tm.has("rate_hz") and tm.dim("frames") == 488
    a, at = read_record(recorded["h5"])
    odd = tmp_path / "Data_odd.h5"
    one = {"measured_modes": a["measured_modes"][:1], "frame_counter": a["frame_counter"][:1]}
    write_record(odd, one, {"configuration": {"observation": {"star": 5}}, "rate_hz": 407.0})
    status, out, err = run(["telemetry", "inspect", odd, "--json"], capsys)
    assert status == 0 and json.loads(out)["star_magnitude_r"] is None and json.loads(out)["format"] == "hdf5", err
    assert run(["telemetry", "convert", odd, tmp_path / "Data_20261126_150000"], capsys)[0] == 0
    assert json.loads(run(["telemetry", "inspect", tmp_path / "Data_20261126_150000", "--json"], capsys)[1])["frames"] == 1


def test_a_one_dimensional_time_filter_gives_the_gains(tmp_path):
    system, _ = _aot_system("shack-hartmann")
    system.loops[0].time_filter_num = aotpy.Image("NUM", np.full(OBS.modes, 0.4, dtype=np.float32))
    path = tmp_path / "num1d.fits"
    system.write_to_file(str(path))
    with open_telemetry(path, required=()) as tm:
        np.testing.assert_allclose(tm.read("gains"), 0.4, rtol=1e-6)


def test_a_chi_table_with_a_delay_for_a_record_without_one(recorded, tmp_path, capsys):
    import h5py

    path = tmp_path / "nodelay.h5"
    import shutil

    shutil.copy(recorded["h5"], path)
    with h5py.File(path, "r+") as f:
        del f.attrs["delay_frames"]
    table = tmp_path / "og.csv"
    table.write_text("mode,optical_gain\n" + "".join(f"{m},0.5\n" for m in range(1, OBS.modes + 1)))
    status, _, err = _offline(path, recorded, capsys, "--delay-frames", "1.6", "--chi-table", table)
    assert status == 0, err


def test_a_measured_rate_is_the_configurations_within_its_tolerance(recorded, tmp_path, capsys):
    """A record whose rate was measured from time stamps (407 Hz x 1.0001) is the configuration's
    407 Hz: offline MGM runs on it and says which rate it used (on today's main: exit 2, the rates
    compared within 1e-6); 1 % off is another loop's record."""
    import shutil

    import h5py

    for factor, status_expected in ((1.0001, 0), (1.01, 2)):
        path = tmp_path / f"rate_{factor}.h5"
        shutil.copy(recorded["h5"], path)
        with h5py.File(path, "r+") as f:
            f.attrs["rate_hz"] = 407.0 * factor
        status, out, err = _offline(path, recorded, capsys)
        assert status == status_expected, err
        if status == 0:
            assert any("407.041 Hz used" in note for note in json.loads(out)["notes"])
        else:
            assert "is not its configuration's (407 Hz)" in err and "within 0.001" in err
