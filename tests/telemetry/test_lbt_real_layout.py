"""LBT tracking-number folders as LBT's supervisor writes them (``lbt_layout``: string cards,
'-9999', 672-wide modes and gains, padded slopes, int32 counters, adsec.sav, a zero-padded
reconstructor), read by every telemetry command; the keywords elab_lib's SOUL path reads, in
the folders soulctl writes; elab_lib's delay model against its own reference values."""

import json

import numpy as np
import pytest
from astropy.io import fits
from cli_run import run
from idl_save import write_sav
from lbt_layout import FLAO_DELAY_FRAMES, SOUL_DELAY_FRAMES, wfs_cards, write_header_only, write_real_folder
from scipy.io import readsav

from soulctl.telemetry.formats import open_telemetry, read_record
from soulctl.telemetry.lbt import elab_lib_delay_s


@pytest.fixture(scope="module")
def real(tmp_path_factory):
    return write_real_folder(tmp_path_factory.mktemp("real-lbt"))


def test_the_fixture_is_the_writers_layout(real):
    """Independently of soulctl: the files have the writer's widths, types and cards."""
    folder, _ = real
    tn = "20190302_190223"
    assert fits.getheader(folder / f"FramesCounter_{tn}.fits")["BITPIX"] == 32
    assert fits.getdata(folder / f"Modes_{tn}.fits").shape[1] == 672 and fits.getdata(folder / f"Slopes_{tn}.fits").shape[1] == 1600
    header = fits.getheader(folder / "wfs.fits")
    assert header["NAXIS"] == 0 and header["HIERARCH ccd39.FRAMERATE"] == "990.00"
    assert readsav(str(folder / "adsec.sav"))["g_gain"].shape == (672,)


def test_every_command_reads_the_real_layout(real, tmp_path, capsys):
    """inspect, psd, identify, convert and offline MGM (exit 2 on today's main: 'must be a
    number, got '990.00'', then 'n_modes must be in 2..671, got 672')."""
    folder, truth = real
    status, out, err = run(["telemetry", "inspect", folder, "--json"], capsys)
    d = json.loads(out)
    assert status == 0 and d["rate_hz"] == 990.0 and d["modes"] == 10 and d["fields"]["slopes"]["shape"] == [3000, 40], err
    assert d["delay_frames"] == pytest.approx(FLAO_DELAY_FRAMES, abs=1e-3) and d["sensor"] == "pyramid"
    notes = " ".join(n["note"] for n in d["notes"])
    assert "computeDelay" in notes and "columns 11-672 are padding" in notes and "columns 41-1600 are padding" in notes
    with open_telemetry(folder, required=()) as tm:
        np.testing.assert_allclose(tm.read("measured_modes"), truth["measured"], atol=1e-4 * np.abs(truth["measured"]).max())
        np.testing.assert_allclose(tm.read("command_modes"), truth["commands"], atol=1e-5 * np.abs(truth["commands"]).max())
        np.testing.assert_allclose(tm.read("gains"), truth["gains"], rtol=1e-6)
    assert run(["telemetry", "psd", folder, "--pseudo-open-loop", "--json"], capsys)[0] == 0
    for target in (tmp_path / "x.h5", tmp_path / "x.fits"):
        assert run(["telemetry", "convert", folder, target], capsys)[0] == 0
        assert read_record(target)[0]["gains"].shape == (10,)
    table = tmp_path / "og.csv"
    table.write_text("mode,optical_gain\n" + "".join(f"{m},{truth['chi']}\n" for m in range(1, 11)))
    status, out, err = run(["optimize", "gains", "--telemetry", folder, "--chi-table", table, "--json"], capsys)
    assert status == 0 and len(json.loads(out)["gains"]) == 10, err


def test_identification_of_the_real_layout_finds_the_loop(real, capsys):
    """The units (m of surface x 2e9, R s x 4e9) and the trimming are right if the plant comes
    out: the delay elab_lib's computeDelay gives, chi = 0.8 in every group."""
    folder, truth = real
    status, out, err = run(["telemetry", "identify", folder, "--json"], capsys)
    assert status == 0, err
    d = json.loads(out)
    assert d["delay_frames"]["value"] == pytest.approx(truth["delay"], abs=0.1)
    for group in d["optical_gains"]:
        assert group["chi"] == pytest.approx(truth["chi"], rel=0.1), group
    assert "turbulence" in d["not_estimated"]  # 10 modes: too few radial orders for the seeing


@pytest.mark.parametrize(
    "cards, field, message",
    [
        (wfs_cards(rate_text="-9999"), "rate_hz", "ccd39.FRAMERATE is '-9999', unknown to its writer"),
        ({k: v for k, v in wfs_cards().items() if k != "ccd39.FRAMERATE"}, "rate_hz", "wfs.fits has no ccd39.FRAMERATE"),
        (wfs_cards(extra={"ccd39.BINNING": "-9999"}), "delay_frames", "ccd39.BINNING"),
        (wfs_cards(extra={"W_UNIT": "MAG"}), "delay_frames", "MagAO's timing is not LBT's"),
    ],
)
def test_unknown_keywords_are_missing_with_the_keyword_named(tmp_path, capsys, cards, field, message):
    folder, _ = write_real_folder(tmp_path, frames=300, cards=cards)
    status, out, err = run(["telemetry", "inspect", folder, "--json"], capsys)
    assert status == 0, err
    d = json.loads(out)
    assert d[field] is None and any(n["field"] == field and message in n["note"] for n in d["notes"]), d["notes"]
    if field == "rate_hz":
        status, _, err = run(["telemetry", "psd", folder], capsys)
        assert status == 2 and "lacks rate_hz" in err and message in err and err.count("\n") == 1


def test_text_that_is_not_a_number_is_refused_naming_the_keyword(tmp_path, capsys):
    folder, _ = write_real_folder(tmp_path, frames=300, cards=wfs_cards(rate_text="fast"))
    status, _, err = run(["telemetry", "inspect", folder], capsys)
    assert status == 2 and "keyword ccd39.FRAMERATE must be a number (or a number as text), got 'fast'" in err


def test_without_the_reconstructor_the_padding_is_what_does_not_vary(tmp_path, capsys):
    """A folder whose reconstructor stayed in the calibration tree: the note names the one
    adsec.sav names; the modes and slopes are the columns up to the last that varies."""
    folder, _ = write_real_folder(tmp_path, frames=300, reconstructor=False)
    status, out, err = run(["telemetry", "inspect", folder, "--json"], capsys)
    d = json.loads(out)
    assert status == 0 and d["modes"] == 10 and d["fields"]["slopes"]["shape"] == [300, 40], err
    assert any("adsec.sav names Rec_20181217_031744.fits" in n["note"] for n in d["notes"])


def test_soul_iir_spare_rows_and_filters_from_the_reconstructor_header(tmp_path, capsys):
    """A SOUL reconstructor whose header carries Tip/Tilt IIR filters (hdr_rec_to_iir_params):
    the modal rows past nmodes_filter are the IIR states, left out and said so; the filters and
    the other modes' forgetting factors are the record's controller."""
    num, den = [0.0, 0.5, -0.3, 1.0], [0.0, 0.2, -1.2, 1.0]  # ascending powers of z: (z^3 - 0.3 z^2 + 0.5 z) / (z^3 - 1.2 z^2 + 0.2 z)
    header = {"MODEIDXN": 2, "MODEIDX0": 0, "MODEIDX1": 1, "IIRNELE0": 4, "IIRNELE1": 1, "FF_NOEXM": 2, "FF_MINVA": 0.9, "FF_EXP": 1.0}
    header |= {f"IIRNUM{i}0": v for i, v in enumerate(num)} | {f"IIRDEN{i}0": v for i, v in enumerate(den)}
    cards = wfs_cards(camera="ocam2", rate_text="500.00")
    folder, _ = write_real_folder(tmp_path, frames=300, n_modes=12, cards=cards, rec_header=header, delay=SOUL_DELAY_FRAMES)
    rec = fits.getdata(next(folder.glob("Rec_*.fits")))
    rec[668:672, :40] = 1e-9  # IIR states: rows past nmodes_filter = 672 - 2*2*3 + 2 = 662
    fits.PrimaryHDU(rec, header=fits.getheader(next(folder.glob("Rec_*.fits")))).writeto(next(folder.glob("Rec_*.fits")), overwrite=True)
    with open_telemetry(folder, required=()) as tm:
        assert tm.dim("n_modes") == 12 and tm.attribute("delay_frames") == pytest.approx(1.70, abs=1e-3)
        b, a = tm.read("controller_num"), tm.read("controller_den")
        np.testing.assert_allclose(b[0, :4], [1.0, -0.3, 0.5, 0.0])
        np.testing.assert_allclose(a[1, :4], [1.0, -1.2, 0.2, 0.0])
        np.testing.assert_allclose(a[2:4, :2], [[1.0, -1.0], [1.0, -1.0]])  # the first FF_NOEXM integrator modes: no leak
        assert a[11, 1] == pytest.approx(-0.9)  # the highest radial order leaks down to FF_MINVA
        assert any("modal rows 669-672 carry the IIR states of modes 1, 2" in n.text for n in tm.notes)


def test_elab_libs_delay_model_against_its_reference_values():
    """elab_lib's test/test_computedelay.ref: FLAO TN 20180129_220007 (binning 4, 993 Hz: the
    summary prints the rate with %d; 2.88773 frames fixes it at 993.54 Hz) 0.00290650 s;
    SOUL TN 20190302_190223 (500 Hz, ocam2 mode 2) 0.00340000 s and 1.70000 frames."""
    flao = elab_lib_delay_s("ccd39", 993.54, binning=4)
    assert flao == pytest.approx(0.00290650, abs=5e-8) and flao * 993.54 == pytest.approx(2.88773, abs=5e-5)
    soul = elab_lib_delay_s("ocam2", 500.0, mode=2)
    assert soul == pytest.approx(0.00340000, abs=5e-9) and soul * 500.0 == pytest.approx(1.70000, abs=1e-6)


# The keywords elab_lib reads of a SOUL wfs.fits (LBTO/elab_lib c0bf6ac): aowfs_status__define.pro
# L18-66 (W_UNIT, the stages, rerotator, lens, ADCs, lamp, cube, sc.*, RR.MODE), L125-127
# (isSoul: ocam2.MODE), aoocam2k__define.pro L14-31 (the camera), aopupils__define.pro L13
# (sc.PUPILS), aoelab__define.pro L249 (sc.DISTURBANCE), aotel__define.pro (tel.TEL.ISTRACKING,
# the operation mode of aoelab L124).
ELAB_LIB_SOUL_KEYWORDS = (
    "W_UNIT", "stagex.POSITION", "stagey.POSITION", "stagez.POSITION", "rerot.POSITION", "lens.POSITION_X", "lens.POSITION_Y",
    "adc1.POSITION", "adc2.POSITION", "lamp.INTENSITY", "cuberot.POSITION", "cubestage.POSITION", "sc.OPTG", "sc.NCPA_TRIGGER",
    "sc.PIXELS_DECIMATION", "sc.SLOPES_DECIMATION", "sc.SLOPENULL", "RR.MODE", "ocam2.FRAMERATE", "ocam2.READOUT_SPEED",
    "ocam2.BINNING", "ocam2.MODE", "ocam2.EM_GAIN", "ocam2.STATUS", "ocam2.DARK_FILENAME", "tt.LAMBDA_D", "sc.PUPILS",
    "sc.DISTURBANCE", "tel.TEL.ISTRACKING",
)  # fmt: skip


def test_a_folder_soulctl_writes_is_soul_to_elab_lib(real, tmp_path, capsys):
    """Every keyword of elab_lib's SOUL path is in the wfs.fits soulctl writes (on today's main
    ocam2.MODE is missing, so elab_lib reads soulctl's output as FLAO), and elab_lib's delay
    model, read from those keywords, is soulctl's camera's."""
    folder, _ = real
    out = tmp_path / "Data_20261207_120000"
    assert run(["telemetry", "convert", folder, out], capsys)[0] == 0
    header = fits.getheader(out / "wfs.fits")
    keys = {k.upper() for k in header}
    missing = [k for k in ELAB_LIB_SOUL_KEYWORDS if k.upper() not in keys and f"HIERARCH {k}".upper() not in keys]
    assert not missing, missing
    assert header["HIERARCH ocam2.FRAMERATE"] == 990.0 and header["HIERARCH tel.TEL.ISTRACKING"] == 1
    assert header["HIERARCH ocam2.MODE"] == 1  # the 0.48 ms read-out of soulctl's delay model (aoocam2k:58)


def test_an_idl_save_file_the_fixtures_write_reads_back(tmp_path):
    path = write_sav(tmp_path / "x.sav", {"g_gain": np.arange(672.0), "m": np.ones((3, 4))}, {"status": {"b0_a": "a/b/Rec_x.fits"}})
    d = readsav(str(path))
    np.testing.assert_array_equal(d["g_gain"], np.arange(672.0))
    assert d["m"].shape == (3, 4) and d["status"]["b0_a"][0] == b"a/b/Rec_x.fits"


def test_the_header_only_wfs_file_of_the_writer(tmp_path):
    """getSetupFits writes a 0-d dummy array: a header without data, which astropy reads."""
    write_header_only(tmp_path / "wfs.fits", wfs_cards())
    with fits.open(tmp_path / "wfs.fits") as h:
        assert h[0].data is None and h[0].header["HIERARCH tel.TEL.ISTRACKING"] == "1"


def test_an_unknown_rate_from_the_system_time_stamps(tmp_path, capsys):
    """SystemTimestamp_<TN>.fits (seconds, aotimestamps__define.pro) gives the rate where the
    camera's keyword is '-9999': 990.07 Hz from the time stamps, said so."""
    folder, _ = write_real_folder(tmp_path, frames=300, cards=wfs_cards(rate_text="-9999"))
    fits.PrimaryHDU(1.7e9 + np.arange(300) / 990.07).writeto(folder / "SystemTimestamp_20190302_190223.fits")
    status, out, err = run(["telemetry", "inspect", folder, "--json"], capsys)
    d = json.loads(out)
    assert status == 0 and d["rate_hz"] == pytest.approx(990.07, rel=1e-6), err
    assert any("from SystemTimestamp_20190302_190223.fits" in n["note"] and "'-9999'" in n["note"] for n in d["notes"])
