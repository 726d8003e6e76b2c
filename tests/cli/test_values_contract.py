"""Values that used to pass validation and then crash or lie, and requests whose cost
exploded: each is refused with exit status 2 and one line, or runs and says what it did."""

import json
import time

import pytest
import tomli_w
from cheap import CHEAP_PYRAMID

from soulctl.cli.app import main
from soulctl.observation import observation_for_magnitude
from soulctl.ranges import MODES

FAST = ["--mag", "16.5", *CHEAP_PYRAMID, "--duration", "0.05"]


def run(args, capsys, cache_dir=None):
    extra = ["--cache-dir", str(cache_dir)] if cache_dir is not None else []
    status = main([str(a) for a in args] + extra)
    out, err = capsys.readouterr()
    return status, out, err


def refused(status, out, err, *words):
    assert status == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for w in words:
        assert w in err, err


# ------------------------------------------------------------------------ observation files


@pytest.mark.parametrize(
    "edit, words",
    [
        (("modes = 90", "modes = 1"), ("modes must be in 2..671",)),
        (("modes = 90", "modes = 672"), ("modes must be in 2..671",)),
        (("magnitude_r = 16.5", "magnitude_r = -60"), ("magnitude_r must be in the look-up table's 0..18.5",)),
        (("magnitude_r = 16.5", "magnitude_r = 99"), ("magnitude_r",)),
        (("magnitude_r = 16.5", "magnitude_r = -30"), ("magnitude_r",)),
        (("zero_point_ph_s_per_subaperture = 264700000.0", "zero_point_ph_s_per_subaperture = 1e300"), ("zero_point",)),
        (("t_asm_ms = 1.0", "t_asm_ms = 1e6"), ("t_asm_ms",)),
        (("frame_rate_hz = 250.0", "frame_rate_hz = 1e9"), ("frame_rate_hz must be in 10..2000 Hz",)),
    ],
)
def test_every_field_of_an_observation_file_is_checked(edit, words, tmp_path, capsys, cache_dir):
    path = tmp_path / "obs.toml"
    observation_for_magnitude(16.5).write_toml(path)
    text = path.read_text()
    assert edit[0] in text
    path.write_text(text.replace(*edit))
    refused(
        *run(["loop", "run", "--config", path, *CHEAP_PYRAMID, "--duration", "0.05"], capsys, cache_dir),
        f"run description {path}",  # loop run reads a run description (an observation file is one)
        *words,
    )


def iir_config(tmp_path, zeros, poles) -> str:
    path = tmp_path / "iir.toml"
    d = observation_for_magnitude(9.7).to_dict()
    d["control"].update(tt_zeros=zeros, tt_poles=poles)
    path.write_text(tomli_w.dumps(d))
    return path


@pytest.mark.parametrize(
    "zeros, poles, words",
    [
        ([1e300, 1e300, 0.0, 0.0], [0.1, 0.2, 0.3, 1.0], ("tt_zeros must be in -10..10",)),
        ([0.1, 0.2, 0.3, 0.4], [1.0, 1.0, 1.0, 1.0], ("unstable at every gain",)),
    ],
)
def test_iir_roots_that_no_loop_can_run_are_refused(zeros, poles, words, tmp_path, capsys, cache_dir):
    refused(*run(["loop", "run", "--config", iir_config(tmp_path, zeros, poles)], capsys, cache_dir), *words)


@pytest.mark.parametrize(
    "row, words",
    [
        ("1700,1e300,0,0,0,0,0,0,1", ("zeros must be in -10..10",)),
        ("1700,0,0,0,0,1,1,1,1", ("unstable at every gain",)),
        ("20,0,0,0,0,0,0,0.5,1", ("no row within 20% of 1700 Hz", "rows at 20 Hz")),
    ],
)
def test_roots_tables_that_do_not_apply_are_refused(row, words, tmp_path, capsys):
    roots = tmp_path / "roots.csv"
    roots.write_text("frame_rate_hz,zero1,zero2,zero3,zero4,pole1,pole2,pole3,pole4\n" + row + "\n")
    refused(*run(["configure", "--mag", "9.7", "--roots", roots], capsys), *words)


@pytest.mark.parametrize(
    "args",
    [
        ["filter", "analyze", "--rate", "1700", "--gain", "0.5", "--zeros", "1e200,1e200", "--poles", "1"],
        ["filter", "analyze", "--rate", "1700", "--gain", "0.5", "--zeros", "1e300", "--poles", "1"],
        ["filter", "analyze", "--rate", "1700", "--gain", "0.5", "--poles", "1e300"],
    ],
)
def test_huge_roots_are_refused(args, capsys):
    refused(*run(args, capsys), "modulus at most 10")


# ------------------------------------------------------------------------------- seeds

SEEDED = [
    ["loop", "run", *FAST],
    ["optimize", "gains", "--mag", "16.5", *CHEAP_PYRAMID],
    ["filter", "design", "--rate", "1700"],
    ["optics", "gains", "--binning", "4", *CHEAP_PYRAMID],
]


@pytest.mark.parametrize("args", SEEDED)
@pytest.mark.parametrize("seed", ["-1", str(2**63), "99999999999999999999999"])
def test_every_seeded_command_refuses_the_same_seeds(args, seed, capsys):
    refused(*run([*args, "--seed", seed], capsys), "--seed must be in 0..2^63-1")


def test_the_largest_seed_runs(capsys, cache_dir):
    status, out, err = run(["loop", "run", *FAST, "--seed", str(2**63 - 1), "--json"], capsys, cache_dir)
    assert status == 0, err


# ---------------------------------------------------------------------- filter analyze


@pytest.mark.parametrize("option, value", [("--gain", "1e-12"), ("--chi", "1e-300")])
def test_gains_too_small_for_the_verdict_are_refused(option, value, capsys):
    args = ["filter", "analyze", "--rate", "1700", "--control", "int", "--gain", "0.3", option, value]
    refused(*run(args, capsys), option)


@pytest.mark.parametrize("gain", ["0.0001", "0.001", "0.3", "0.5", "0.55", "1", "100"])
def test_the_verdict_follows_from_the_gain_margin(gain, capsys):
    status, out, err = run(["filter", "analyze", "--rate", "1700", "--control", "int", "--gain", gain, "--json"], capsys)
    c = json.loads(out)["controllers"][0]
    assert c["stable"] == (c["gain_margin"] == "inf" or c["gain_margin"] > 1)
    assert c["stable"] == (float(gain) < c["max_stable_gain"])
    assert status == (0 if c["stable"] else 3)


@pytest.mark.parametrize(
    "args, words",
    [
        (["--rate", "1700", "--delay-ms", "10000"], ("frames: accepted 0..50 frames",)),
        (["--rate", "1700", "--delay-frames", "1000"], ("--delay-frames must be in 0..50 frames",)),
        (["--rate", "1e6"], ("--rate must be in 1..100000 Hz",)),
        (["--rate", "1e5"], ("SOUL delay model at 100000 Hz", "accepted 0..50 frames")),
        (["--rate", ",".join(["1000"] * 17)], ("accepted at most 16",)),
    ],
)
def test_analysis_requests_beyond_what_it_can_do_in_seconds_are_refused(args, words, capsys):
    t0 = time.perf_counter()
    refused(*run(["filter", "analyze", "--gain", "0.3", *args], capsys), *words)
    assert time.perf_counter() - t0 < 2


def test_the_costliest_accepted_analysis_takes_seconds(capsys):
    t0 = time.perf_counter()
    status, out, err = run(
        [
            "filter",
            "analyze",
            "--rate",
            ",".join(["1e5"] * 16),
            "--gain",
            "0.01",
            "--delay-frames",
            "50",
            "--control",
            "iir",
            "--zeros",
            "0.5,0.5,0.5,0.5,0.5,0.5,0.5,0.5",
            "--poles",
            "1,0.9,0.8,0.7,0.6,0.5,0.4,0.3",
            "--json",
        ],
        capsys,
    )
    assert status in (0, 3), err
    assert time.perf_counter() - t0 < 10


@pytest.mark.parametrize("rate", ["1", "20", "99", "2001", "1e6"])
def test_design_rates_outside_the_method_are_refused(rate, capsys):
    refused(*run(["filter", "design", "--rate", rate], capsys), "--rate must be in 100..2000 Hz")


def test_design_delays_beyond_the_method_are_refused(capsys):
    refused(*run(["filter", "design", "--rate", "1700", "--delay-ms", "29"], capsys), "49.3 frames: the design accepts 0..10 frames")


# ---------------------------------------------------------------------------- vibrations


@pytest.mark.parametrize(
    "field, value, words",
    [
        ("damping", "1e-300", ("damping must be in 0.0001..0.9",)),
        ("frequency_hz", "1e-300", ("frequency_hz must be in 0.1..1000 Hz",)),
        ("tip_mas", "999999", ("tip_mas must be in 0..1000 mas",)),
    ],
)
def test_vibration_lines_outside_their_physical_range_are_refused(field, value, words, tmp_path, capsys, cache_dir):
    line = {"frequency_hz": "13.0", "damping": "0.02", "tip_mas": "9.0", "tilt_mas": "6.5", field: value}
    vib = tmp_path / "vib.toml"
    vib.write_text("[[line]]\n" + "".join(f"{k} = {v}\n" for k, v in line.items()))
    for args in (["loop", "run", *FAST], ["filter", "design", "--rate", "1700"]):
        refused(*run([*args, "--vibrations", vib], capsys, cache_dir if args[0] == "loop" else None), "line 1", *words)


def test_the_whole_magnitude_range_runs_with_default_options(capsys, cache_dir):
    """R18.4 runs at ~100 Hz: the default 58 Hz vibration line is above its Nyquist frequency
    and is left out with a note, not a refusal."""
    status, out, err = run(["loop", "run", "--mag", "18.4", *CHEAP_PYRAMID, "--json"], capsys, cache_dir)
    assert status == 0, err
    notes = json.loads(out)["notes"]
    assert any("58 Hz vibration line is left out" in n for n in notes)


# --------------------------------------------------------------------------- the user's terms


def test_wind_errors_are_in_the_users_terms(capsys, cache_dir):
    status, out, err = run(["loop", "run", *FAST, "--wind", "99", "--json"], capsys, cache_dir)
    assert status == 0, err
    refused(*run(["loop", "run", *FAST, "--wind", "100.0001"], capsys, cache_dir), "--wind must be in 0..100 m/s (> 0), got 100.0001")


def test_a_probe_slower_than_the_update_is_refused(capsys, cache_dir):
    args = [
        "loop",
        "run",
        "--mag",
        "16.5",
        *CHEAP_PYRAMID,
        "--duration",
        "2",
        "--ogtl",
        "--period",
        "0.1",
        "--probe-frequency",
        "0.001",
    ]
    refused(*run(args, capsys, cache_dir), "--probe-frequency 0.001 Hz", "at least 4")


def test_a_run_too_short_for_a_metric_reports_it_as_not_available(capsys, cache_dir):
    status, out, err = run(["loop", "run", "--mag", "16.5", *CHEAP_PYRAMID, "--duration", "0.0001", "--json"], capsys, cache_dir)
    assert status == 0, err
    m = json.loads(out, parse_constant=lambda c: pytest.fail(f"{c} in JSON"))["metrics"]
    assert m["tt_jitter_mas"] is None and m["tt_jitter_pol_3hz_mas"] is None and m["rejection_13hz"] is None
    status, out, err = run(["loop", "run", "--mag", "16.5", *CHEAP_PYRAMID, "--duration", "0.0001"], capsys, cache_dir)
    assert "n/a (loop not settled" in out and "nan" not in out and "0.00 mas" not in out


def test_a_loop_that_has_not_settled_has_no_closed_loop_figures(capsys, cache_dir):
    """10 frames at 250 Hz: the metrics would start 5 frames in, before the 10 frames the loop
    needs to close (a Strehl ratio of 0.02 there, the loop's is ~0.1); 20 frames settle it."""
    args = ["loop", "run", "--mag", "16.5", *CHEAP_PYRAMID, "--duration", "0.039", "--json"]
    status, out, err = run(args, capsys, cache_dir)
    assert status == 0, err
    m = json.loads(out)["metrics"]
    assert m["strehl"] is None and m["residual_nm"] is None and "loop not settled" in m["not_available"]["strehl"]
    status, out, err = run([*args[:-2], "0.08", "--json"], capsys, cache_dir)
    assert json.loads(out)["metrics"]["strehl"] is not None


@pytest.mark.slow
def test_no_line_no_rejection(capsys, cache_dir):
    """Without vibrations there is no 13 Hz line: the rejection is not a figure of the run."""
    args = ["loop", "run", "--mag", "14.51", *CHEAP_PYRAMID, "--duration", "1", "--no-vibrations", "--json"]
    status, out, err = run(args, capsys, cache_dir)
    assert status == 0, err
    m = json.loads(out)["metrics"]
    assert m["rejection_13hz"] is None and "no line at 13 Hz" in m["not_available"]["rejection_13hz"]


def test_unicode_digits_are_the_same_digits(capsys):
    assert run(["configure", "--mag", "１３", "--json"], capsys)[1] == run(["configure", "--mag", "13", "--json"], capsys)[1]
    assert run(["configure", "--mag", "١٣", "--json"], capsys)[1] == run(["configure", "--mag", "13", "--json"], capsys)[1]


# ---------------------------------------------------------------------- ranges that agree


@pytest.mark.parametrize(
    "args",
    [
        ["loop", "run", *FAST],
        ["optimize", "gains", "--mag", "16.5", *CHEAP_PYRAMID],
        ["optics", "atmosphere"],
        ["optics", "gains", "--binning", "4", *CHEAP_PYRAMID],
        ["filter", "design", "--rate", "1700"],
    ],
)
@pytest.mark.parametrize(
    "option, value, words",
    [
        ("--L0", "0.001", "--L0 must be in 0.5..10000 m, got 0.001"),
        ("--seeing", "10.5", "--seeing must be in 0.05..10 arcsec, got 10.5"),
    ],
)
def test_one_range_for_every_command(args, option, value, words, capsys):
    refused(*run([*args, option, value], capsys), words)


def test_mode_counts_agree_with_the_mirror(optics_cache):
    from soulctl.optics.calibration import BasisSetup, modal_basis

    assert MODES.hi == modal_basis(BasisSetup(), optics_cache).n_modes


def test_under_determined_calibrations_are_refused(capsys, cache_dir):
    refused(
        *run(["optics", "calibrate", "--binning", "4", "--modes", "671"], capsys, cache_dir),
        "cannot be calibrated from the",
        "accepted at most",
    )


# ------------------------------------------------------------------------------ gain files


def test_a_binary_gain_file_is_refused(tmp_path, capsys, cache_dir):
    gains = tmp_path / "gains.csv"
    gains.write_bytes(bytes(range(256)) * 4)
    refused(*run(["loop", "run", *FAST, "--gains", gains], capsys, cache_dir), "is not UTF-8 text")


def test_gain_files_are_applied_by_their_mode_column(tmp_path, capsys, cache_dir):
    """A mode,gain file in another order (and with a BOM, as spreadsheets save it) is applied
    by mode number, not by line."""
    wanted = [0.3, 0.28] + [round(0.25 - 0.001 * i, 3) for i in range(88)]
    lines = [f"{m},{g}" for m, g in enumerate(wanted, 1)][::-1]
    gains = tmp_path / "gains.csv"
    gains.write_text("\ufeffmode,gain\n" + "\n".join(lines) + "\n")
    status, out, err = run(["loop", "run", *FAST, "--gains", gains, "--json"], capsys, cache_dir)
    assert status == 0, err
    assert json.loads(out)["configuration"]["gains"]["modes"] == wanted
    gains.write_text("mode,gain\n1,0.3\n1,0.3\n" + "\n".join(f"{m},0.2" for m in range(3, 91)) + "\n")
    refused(*run(["loop", "run", *FAST, "--gains", gains], capsys, cache_dir), "the modes must be 1..90, each once")


# --------------------------------------------------------- what adversarial testing found


def test_offline_optimisation_checks_every_option(tmp_path, capsys, cache_dir):
    h5 = tmp_path / "t.h5"
    h5.write_bytes(b"not read: the options are checked first")
    for option, value, words in [
        ("--seeing", "nan", "--seeing must be in"),
        ("--seed", "-3", "--seed must be in"),
        ("--duration", "nan", "--duration must be in"),
        ("--probe-mode", "9999", "--probe-mode must be in"),
        ("--oversampling", "99", "--oversampling must be in"),
        ("--period", "-1", "--period must be in"),
        ("--gains", "99,99,99", "--gains must be TT,MID,HIGH"),
        ("--tt-control", "foo", "--tt-control"),
    ]:
        refused(*run(["optimize", "gains", "--telemetry", h5, option, value], capsys, cache_dir), words)


def test_calibration_and_loop_refuse_the_same_sampling(capsys, cache_dir):
    refused(
        *run(["optics", "calibrate", "--binning", "3", "--modes", "91", *CHEAP_PYRAMID], capsys, cache_dir),
        "accepted up to 90 modes",
    )


@pytest.mark.slow
@pytest.mark.parametrize(
    "args",
    [
        ["optics", "atmosphere", "--seeing", "١", "--json"],
        ["optics", "atmosphere", "--seeing", "１", "--json"],
        ["optics", "atmosphere", "--wind", "1_0", "--json"],
        ["filter", "design", "--rate", "1700", "--seed", "１", "--epsilon", "٠.٢", "--json"],
    ],
)
def test_every_numeric_option_reads_numbers_the_same_way(args, capsys):
    status, out, err = run(args, capsys)
    assert status == 0, err
    json.loads(out)


@pytest.mark.parametrize(
    "args, words",
    [
        (["optics", "atmosphere", "--seeing", "abc"], "must be a number in 0.05..10 arcsec, got 'abc'"),
        (["optics", "gains", "--screens", "1.5"], "must be an integer in 1..64, got '1.5'"),
        (["loop", "run", *FAST, "--oversampling", "1.5"], "must be an integer in 1..4, got '1.5'"),
    ],
)
def test_a_text_that_is_not_a_number_is_refused_with_the_range(args, words, capsys):
    refused(*run(args, capsys), words)


def test_an_integral_float_is_an_integer(capsys, cache_dir):
    a = run(["loop", "run", *FAST, "--seed", "3", "--json"], capsys, cache_dir)
    b = run(["loop", "run", *FAST, "--seed", "3.0", "--json"], capsys, cache_dir)
    assert a[0] == b[0] == 0 and json.loads(a[1])["metrics"] == json.loads(b[1])["metrics"]


@pytest.mark.parametrize(
    "gains, words",
    [
        ("0.3,9,0.2", "modes 3-90 gain 9 is unstable"),  # 90 modes: modes 3-90, no group 121-last
    ],
)
def test_stability_refusals_name_the_groups_the_loop_has(gains, words, capsys, cache_dir):
    refused(*run(["loop", "run", *FAST, "--gains", gains], capsys, cache_dir), words)
    # the gain of a group the loop does not have is not checked: it applies to no mode
    status, out, err = run(["loop", "run", *FAST, "--gains", "0.3,0.2,9", "--json"], capsys, cache_dir)
    assert status == 0, err


def test_stability_refusals_name_the_mode_of_a_gain_file(tmp_path, capsys, cache_dir):
    gains = tmp_path / "g.toml"
    gains.write_text("gains = [" + ", ".join(["0.2"] * 10 + ["9"] + ["0.2"] * 79) + "]\n")
    refused(*run(["loop", "run", *FAST, "--gains", gains], capsys, cache_dir), "mode 11 gain 9 is unstable")


def test_a_period_no_run_can_hold_is_refused_as_such(capsys, cache_dir):
    refused(*run(["loop", "run", *FAST, "--mgm", "--period", "600"], capsys, cache_dir), "shorten --period")


@pytest.mark.parametrize(
    "args, words",
    [
        (["loop", "run", *FAST, "--ogtl", "--probe-amplitude", "1e-300"], "--probe-amplitude must be in 0.1..1000 nm"),
    ],
)
def test_probes_below_any_signal_are_refused(args, words, capsys, cache_dir):
    refused(*run(args, capsys, cache_dir), words)


def test_roots_table_rates_are_frame_rates(tmp_path, capsys):
    roots = tmp_path / "roots.csv"
    roots.write_text("frame_rate_hz,zero1,zero2,zero3,zero4,pole1,pole2,pole3,pole4\n1e300,0,0,0,0,0,0,0.5,1\n")
    refused(*run(["configure", "--mag", "9.7", "--roots", roots], capsys), "frame rate must be in 10..2000 Hz")


def test_vibration_files_refuse_unknown_keys(tmp_path, capsys, cache_dir):
    vib = tmp_path / "vib.toml"
    vib.write_text("[[line]]\nfrequency_hz = 13.0\ndamping = 0.02\ntip_mas = 9.0\ntilt_mas = 6.5\namplitude = 3\n")
    refused(*run(["loop", "run", *FAST, "--vibrations", vib], capsys, cache_dir), "unknown key amplitude")
