"""`soulctl optimize gains --method mgm --telemetry FILE` on damaged and implausible files:
exit 2 with one line naming the field (nothing written), or exit 0 with gains that `loop run
--gains` accepts - never a traceback."""

import dataclasses
import json
import math

import h5py
import numpy as np
import pytest
from cheap import CHEAP_PYRAMID
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from soulctl.cli.app import main
from soulctl.cli.common import parse_gains
from soulctl.control.gains import check_stability
from soulctl.control.structure import StructuralResonance, sampled_structure
from soulctl.observation import observation_for_magnitude
from soulctl.ranges import LOOP_GAIN

# test_optimize's small loop: 54 modes at 407 Hz on a 40-px pupil, with an R11 star's flux
OBS = dataclasses.replace(observation_for_magnitude(17), magnitude_r=11.0)
N = OBS.modes


@pytest.fixture(scope="module")
def env(tmp_path_factory, optics_cache):
    """The session's cache, the configuration and one recorded loop (1.2 s at fixed gains:
    488 frames, four Welch segments of 128)."""
    root = tmp_path_factory.mktemp("offline")
    config = root / "small.toml"
    OBS.write_toml(config)
    recorded = root / "loop.h5"
    status = main(
        [
            "loop",
            "run",
            "--config",
            str(config),
            *CHEAP_PYRAMID,
            "--seeing",
            "0.6",
            "--duration",
            "1.2",
            "--telemetry",
            str(recorded),
            "--telemetry-fields",
            "all",
            "--cache-dir",
            str(optics_cache.directory),
            "--json",
        ]
    )
    assert status == 0
    return {"root": root, "config": config, "recorded": recorded, "cache": optics_cache.directory}


def offline(path, env, capsys, *args):
    out_file = env["root"] / "gains.toml"
    out_file.unlink(missing_ok=True)
    status = main(
        [
            "optimize",
            "gains",
            "--method",
            "mgm",
            "--telemetry",
            str(path),
            "--json",
            "--out",
            str(out_file),
            "--cache-dir",
            str(env["cache"]),
            *args,
        ]
    )
    out, err = capsys.readouterr()
    return status, out, err, out_file


def edited(env, change, name="edited.h5"):
    path = env["root"] / name
    path.write_bytes(env["recorded"].read_bytes())
    with h5py.File(path, "r+") as f:
        change(f)
    return path


def replace(name, make):
    def change(f):
        data = make(f[name][()])
        del f[name]
        f[name] = data

    return change


def set_attr(name, value):
    return lambda f: f.attrs.__setitem__(name, value)


def set_config(path, value):
    """Set configuration member ``path`` (dotted) to ``value`` in the JSON attribute."""

    def change(f):
        conf = json.loads(f.attrs["configuration"])
        *outer, key = path.split(".")
        section = conf
        for part in outer:
            section = section[part]
        section[key] = value
        f.attrs["configuration"] = json.dumps(conf)

    return change


def accepted_by_loop_run(gains_file) -> np.ndarray:
    """The gains of ``gains_file`` after `loop run --gains`'s own checks (the file's parser,
    the range, the nominal stability with the default resonance and with --no-resonance)."""
    gains = parse_gains(str(gains_file), 0.99)
    g = gains.per_mode(N)
    assert np.all((g >= LOOP_GAIN.lo) & (g <= LOOP_GAIN.hi))
    for structure in (StructuralResonance(), None):
        check_stability(OBS, gains, sampled_structure(structure, OBS.frame_rate_hz))
    return g


def assert_refused(status, err, out_file, message):
    assert status == 2, err
    assert message in err, err
    assert err.count("\n") == 1 and err.startswith("soulctl: error:") and "Traceback" not in err
    assert not out_file.exists()


def test_a_recorded_loop_gives_gains_loop_run_accepts(env, capsys):
    status, out, err, out_file = offline(env["recorded"], env, capsys)
    assert status == 0, err
    d = json.loads(out)
    g = accepted_by_loop_run(out_file)
    np.testing.assert_allclose(g, d["gains"], atol=1e-5)
    assert d["window"]["frames"] == 488 and d["window"]["welch_segment"] == 128
    # and `loop run` itself runs them
    assert (
        main(
            [
                "loop",
                "run",
                "--config",
                str(env["config"]),
                *CHEAP_PYRAMID,
                "--duration",
                "0.05",
                "--gains",
                str(out_file),
                "--cache-dir",
                str(env["cache"]),
                "--json",
            ]
        )
        == 0
    )
    capsys.readouterr()


def test_gains_above_the_nominal_limit_are_capped_and_reported(env, capsys):
    """Recorded gains of 5 (in 0..10, beyond the nominal limit): MGM's update keeps half of
    them, above what `loop run` accepts; every mode is capped and the file is still accepted."""
    path = edited(env, lambda f: (f.__delitem__("gain_history"), f["gains"].__setitem__(slice(None), 5.0)))
    status, out, err, out_file = offline(path, env, capsys)
    assert status == 0, err
    d = json.loads(out)
    assert d["capped_modes"] == list(range(1, N + 1))
    accepted_by_loop_run(out_file)


@pytest.mark.parametrize(
    "change, message",
    [
        # tracebacks before: non-numbers and arrays where a number belongs
        (set_attr("rate_hz", "fast"), "attribute rate_hz must be a number in 0..100000 Hz (> 0), got 'fast'"),
        (set_attr("rate_hz", [407.0, 407.0]), "attribute rate_hz must be a number in 0..100000 Hz (> 0), got an array of shape (2,)"),
        (set_attr("delay_frames", "1.6"), "attribute delay_frames must be a number in 0..50 frames, got '1.6'"),
        (set_attr("delay_frames", [1.6, 1.6]), "attribute delay_frames must be a number in 0..50 frames, got an array"),
        (set_attr("diverged_at", "no"), "attribute diverged_at must be an integer in -1..2^63-1, got 'no'"),
        (set_attr("diverged_at", [-1, -1]), "attribute diverged_at must be an integer in -1..2^63-1, got an array"),
        (set_config("oversampling", "two"), "attribute configuration.oversampling must be an integer in 1..4, got 'two'"),
        (set_config("oversampling", [1, 2]), "attribute configuration.oversampling must be an integer in 1..4, got a JSON array"),
        (replace("measured_modes", lambda a: a.astype("S8")), "field measured_modes holds text"),
        (lambda f: (f.__delitem__("command_modes"), f.create_group("command_modes")), "field command_modes is a group, expected a dataset"),
        (replace("sensitivity", lambda a: a[:, None]), "field sensitivity has shape (488, 1), expected (frames,)"),
        (
            replace("gain_history/gains", lambda a: np.concatenate([a, a])),
            "field gain_history/gains has 2 entries, gain_history/frames has 1",
        ),
        # silently accepted before
        (set_attr("rate_hz", np.nan), "attribute rate_hz must be a number in 0..100000 Hz (> 0), got nan"),
        (replace("measured_modes", lambda a: a + 1j), "field measured_modes holds complex numbers"),
        (replace("gain_history/frames", lambda a: a - 5), "field gain_history/frames must hold integers in 0..2^63-1, got -5"),
        (
            replace("gain_history/frames", lambda a: a + 10**12),
            "field gain_history/frames holds frame 1000000000000, beyond the file's 488 frames",
        ),
        (replace("gain_history/frames", lambda a: a[:, None]), "field gain_history/frames has shape (1, 1), expected (changes,)"),
        (set_config("gains.forgetting", True), "attribute configuration.gains.forgetting must be a number in 0..1, got True"),
        # garbage that gave garbage: gains loop run refuses
        (replace("gains", lambda a: -a), "field gains must hold real numbers in 0..10, got -"),
        (replace("gain_history/gains", lambda a: a * 1e6), "field gain_history/gains must hold real numbers in 0..10, got"),
        (replace("measured_modes", np.zeros_like), "field measured_modes has no signal in mode 1 and 53 more"),
        (lambda f: f["measured_modes"].__setitem__((slice(None), 7), 2.5), "field measured_modes has no signal in mode 8 "),
        # the rest of the contract
        (set_attr("delay_frames", 2.5), "attribute delay_frames is 2.5 frames but the configuration's delay is 1.61457 frames"),
        (set_attr("diverged_at", 400), "records a loop that diverged (frame 400)"),
        (set_config("structure", {"frequency_hz": 1e400}), "attribute configuration.structure.frequency_hz must be a finite number"),
        (set_config("observation", {"star": 1}), "attribute configuration.observation is not an observation"),
        (set_attr("run_description", "[star\n"), "attribute run_description is not TOML"),
        (set_attr("run_description", "[atmosphere]\nseeing = 1.0\n"), "[atmosphere] has the unknown key 'seeing'"),
        (set_attr("run_description", "[run]\nseed = -1\n"), "run.seed must be in 0..2^63-1"),
    ],
)
def test_bad_fields_exit_2_with_one_line(env, capsys, change, message):
    status, out, err, out_file = offline(edited(env, change), env, capsys)
    assert_refused(status, err, out_file, message)


def test_a_file_that_is_not_hdf5_exits_2(env, capsys):
    text = env["root"] / "notes.h5"
    text.write_text("frames,gain\n")
    status, _, err, out_file = offline(text, env, capsys)
    assert_refused(status, err, out_file, "is not an HDF5 file")


def test_only_the_needed_fields_and_rows_are_read(env, capsys):
    """Values of fields offline MGM does not use (slopes) and of frames before its window are
    not read: NaN there does not matter; their layout still does."""

    def change(f):
        f["slopes"][5, 5] = np.nan
        f["flux"][0] = np.nan

    status, out, err, _ = offline(edited(env, change), env, capsys)
    assert status == 0, err
    path = edited(env, lambda f: (f["measured_modes"].__setitem__((0, 0), np.nan), f["sensitivity"].__setitem__(slice(0, 100), 2.0)))
    status, out, err, _ = offline(path, env, capsys)
    assert status == 0, err
    assert json.loads(out)["window"]["first_frame"] == 100
    # the table says where the window starts and why (a record at fixed gains and k: all of it)
    status = main(["optimize", "gains", "--method", "mgm", "--telemetry", str(path), "--cache-dir", str(env["cache"])])
    table = capsys.readouterr().out
    assert status == 0 and "from frame 100: the frames after the last change of the gains or k" in " ".join(table.split())
    status, _, err, out_file = offline(edited(env, replace("slopes", lambda a: a[:10])), env, capsys)
    assert_refused(status, err, out_file, "field slopes has 10 frames")


# ------------------------------------------------------------------- property-based test

DATASET_NAMES = ("measured_modes", "command_modes", "gains", "sensitivity", "gain_history/frames", "gain_history/gains", "slopes", "flux")
ATTRIBUTE_NAMES = ("rate_hz", "delay_frames", "diverged_at", "n_modes", "configuration", "run_description")
CONFIG_MEMBERS = ("oversampling", "gains.forgetting", "structure", "structure.damping", "observation", "observation.control.modes")
SPECIAL = st.sampled_from([math.nan, math.inf, -math.inf, -1.0, 0.0, 1e-300, 1e30, 1e308, -1e6, 5.0, 2**63, -(2**63)])
NUMBER = st.one_of(SPECIAL, st.floats(allow_nan=True, allow_infinity=True), st.integers(-(2**70), 2**70))
ATTR_VALUE = st.one_of(
    NUMBER,
    st.text(max_size=8),
    st.booleans(),
    st.complex_numbers(allow_nan=True),
    st.lists(st.floats(allow_nan=True), min_size=0, max_size=3),
    st.just(b"\xff\xfe"),
)
JSON_VALUE = st.recursive(
    st.one_of(st.none(), st.booleans(), NUMBER, st.text(max_size=5)),
    lambda inner: st.one_of(st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=5), inner, max_size=3)),
    max_leaves=6,
)


def _dataset_edit(name, how, value):
    def change(f):
        if name not in f:
            return
        data = f[name][()]
        if how == "element":
            flat = data.reshape(-1).astype(float)
            if flat.size:
                flat[len(flat) // 2] = value
            data = flat.reshape(data.shape)
        elif how == "all":
            data = np.full(data.shape, value)
        elif how == "complex":
            data = data + 1j
        elif how == "text":
            data = data.astype("S12")
        elif how == "bool":
            data = data != 0
        elif how == "transpose":
            data = data.T[..., None] if data.ndim == 1 else data.T
        elif how == "truncate":
            data = data[: max(0, len(data) // 3)]
        elif how == "extra-axis":
            data = data[..., None]
        elif how == "scale":
            data = data * value
        elif how == "scalar":
            data = np.float64(value)
        del f[name]
        if how == "group":
            f.create_group(name)
        elif how != "delete":
            f[name] = data

    return change


def _gains_edit(gains):
    def change(f):
        f["gains"][:] = gains
        f["gain_history/gains"][-1] = gains

    return change


# plausible files: recorded gains anywhere in 0..10, measurements scaled, k changed
PLAUSIBLE = st.one_of(
    st.builds(_gains_edit, st.lists(st.floats(0.0, 10.0), min_size=N, max_size=N).map(np.array)),
    st.builds(
        lambda name, factor: _dataset_edit(name, "scale", factor),
        st.sampled_from(["measured_modes", "command_modes"]),
        st.floats(1e-6, 1e3),
    ),
    st.builds(lambda k: _dataset_edit("sensitivity", "all", k), st.floats(0.05, 20.0)),
)
EDIT = st.one_of(
    PLAUSIBLE,
    st.builds(
        _dataset_edit,
        st.sampled_from(DATASET_NAMES),
        st.sampled_from(
            ["element", "all", "scale", "complex", "text", "bool", "transpose", "truncate", "extra-axis", "scalar", "group", "delete"]
        ),
        NUMBER.filter(lambda v: not isinstance(v, int) or abs(v) < 2**63).map(float),
    ),
    st.builds(lambda name, value: set_attr(name, value), st.sampled_from(ATTRIBUTE_NAMES), ATTR_VALUE),
    st.builds(lambda name: lambda f: f.attrs.__delitem__(name) if name in f.attrs else None, st.sampled_from(ATTRIBUTE_NAMES)),
    st.builds(lambda member, value: _config_edit(member, value), st.sampled_from(CONFIG_MEMBERS), JSON_VALUE),
)


def _config_edit(member, value):
    def change(f):
        try:
            set_config(member, value)(f)
        except (KeyError, TypeError):  # a member under a replaced one: nothing to edit
            pass

    return change


@pytest.mark.slow
@settings(
    max_examples=60, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow]
)
@given(edits=st.lists(EDIT, min_size=1, max_size=3))
def test_any_corruption_exits_2_with_one_line_or_0_with_gains_loop_run_accepts(env, capsys, edits):
    def change(f):
        for e in edits:
            try:
                e(f)
            except (TypeError, ValueError, OverflowError, OSError, KeyError):  # h5py cannot store that value (e.g. real gains
                pass  # into a dataset an earlier edit made complex, or under a deleted group): that edit does not apply

    path = edited(env, change, "property.h5")
    status, out, err, out_file = offline(path, env, capsys)
    assert status in (0, 2), err
    if status == 2:
        assert err.count("\n") == 1 and err.startswith("soulctl: error:") and "Traceback" not in err
        assert not out_file.exists()
    else:
        g = accepted_by_loop_run(out_file)
        np.testing.assert_allclose(g, json.loads(out)["gains"], atol=1e-5)


@pytest.mark.slow
def test_the_recorded_probe_mode_sets_mgms_plant(env, capsys, tmp_path):
    """A run made with --probe-mode 10: offline MGM takes chi_i = gamma_i / gamma_10 (it assumed
    mode 30, the default, whatever the run had probed); a file whose probe mode is not a mode
    is refused, and so is one whose OGTL never acted on an estimate (k never calibrated)."""
    h5 = tmp_path / "probe10.h5"
    status = main(
        [
            "loop",
            "run",
            "--config",
            str(env["config"]),
            *CHEAP_PYRAMID,
            "--seeing",
            "0.6",
            "--duration",
            "2.5",
            "--ogtl",
            "--probe-mode",
            "10",
            "--period",
            "1",
            "--telemetry",
            str(h5),
            "--cache-dir",
            str(env["cache"]),
            "--json",
        ]
    )
    assert status == 0
    capsys.readouterr()
    status, out, err, _ = offline(h5, env, capsys)
    assert status == 0, err
    d = json.loads(out)
    assert d["ogtl"] and d["probe_mode"] == 10
    as_30 = tmp_path / "probe30.h5"
    as_30.write_bytes(h5.read_bytes())
    with h5py.File(as_30, "r+") as f:
        f["aux/ogtl/mode"][...] = 30
    status, out, err, _ = offline(as_30, env, capsys)
    d30 = json.loads(out)
    assert d30["probe_mode"] == 30 and not np.allclose(d30["optimum"], d["optimum"])
    with h5py.File(as_30, "r+") as f:
        f["aux/ogtl/mode"][-1] = 0  # not a mode
    status, _, err, out_file = offline(as_30, env, capsys)
    assert (
        status == 2
        and not out_file.exists()
        and "/aux/ogtl/mode must hold the probed mode, an integer in 1..54" in err
        and err.count("\n") == 1
    )
    # a run whose OGTL never acted on an estimate: k uncalibrated, MGM's plant unknown
    from soulctl.control import ogtl

    with h5py.File(h5, "r") as f:
        statuses = f["aux/ogtl/status"][...]
    assert not np.isin(statuses, (ogtl.LOW_SNR, ogtl.GROWING, ogtl.NO_ESTIMATE)).all()  # this run's OGTL acted
    held = tmp_path / "held.h5"
    held.write_bytes(h5.read_bytes())
    with h5py.File(held, "r+") as f:
        f["aux/ogtl/status"][...] = ogtl.LOW_SNR
    status, _, err, out_file = offline(held, env, capsys)
    assert status == 2 and not out_file.exists() and "OGTL never acted on a reliable estimate" in err and err.count("\n") == 1
    for bad in (np.full(statuses.shape, np.nan), np.full(statuses.shape, 7), np.array([b"updated"] * statuses.size)):
        with h5py.File(held, "r+") as f:
            del f["aux/ogtl/status"]
            f["aux/ogtl/status"] = bad
        status, _, err, out_file = offline(held, env, capsys)
        assert status == 2 and not out_file.exists() and "aux/ogtl/status" in err and err.count("\n") == 1  # text: the schema's own refusal
        assert bad.dtype.kind == "S" or "/aux/ogtl/status must hold OGTL's update statuses, integers in 0..6" in err
