"""The telemetry schema and its reader, on small synthetic files: the documented layout is the
schema's, and every way a field can be wrong is an InputError naming it."""

import os
import re

import h5py
import numpy as np
import pytest

from soulctl.errors import InputError
from soulctl.telemetry import hdf5 as telemetry_file
from soulctl.telemetry.formats import read_telemetry
from soulctl.telemetry.hdf5 import write_telemetry
from soulctl.telemetry.schema import DATASETS, TELEMETRY_SCHEMA, TelemetryReader

FRAMES, MODES = 40, 3


def arrays(frames=FRAMES, modes=MODES):
    rng = np.random.default_rng(0)
    return {
        "slopes": rng.normal(size=(frames, 8)),
        "measured_modes": rng.normal(size=(frames, modes)),
        "commands": rng.normal(size=(frames, 5)),
        "command_modes": rng.normal(size=(frames, modes)),
        "residual_rms_nm": np.abs(rng.normal(size=frames)),
        "frame_time_s": np.arange(frames) / 400.0,
        "sensitivity": np.ones(frames),
        "flux": rng.normal(100, 1, frames),
        "gains": np.full(modes, 0.4),
        "gain_history/frames": np.array([0, 10], dtype=np.int64),
        "gain_history/gains": np.array([np.full(modes, 0.3), np.full(modes, 0.4)]),
        "aux/ogtl/frame": np.array([10], dtype=np.int64),
        "aux/ogtl/optical_gain": np.array([np.nan]),  # NaN: no estimate, allowed in records
    }


@pytest.fixture
def h5(tmp_path):
    path = tmp_path / "tm.h5"
    write_telemetry(path, arrays(), {"rate_hz": 400.0, "delay_frames": 1.5, "n_modes": MODES, "diverged_at": -1}, {"oversampling": 1})
    return path


def edit(path, change):
    with h5py.File(path, "r+") as f:
        change(f)
    return path


def replace(name, data):
    def change(f):
        del f[name]
        f[name] = data

    return change


def test_the_documented_layout_is_the_schema():
    """Each /name (shape) dtype line of telemetry_file's docstring is a field of the schema
    with that shape and dtype, and every dataset of the schema is documented."""
    doc = telemetry_file.__doc__
    lines = re.findall(r"^\s+/(\S+)\s+(\([^)]*\))\s+(\w+)", doc, re.M)
    documented = {name: (shape, dtype) for name, shape, dtype in lines}
    assert set(documented) == {f.name for f in DATASETS} | {"aux/<task>/<field>"}
    for name, (shape, dtype) in documented.items():
        field = TELEMETRY_SCHEMA[name]
        assert dtype == field.stored, name
        if field.shape[:1] != ("updates",):
            assert shape == field.shape_text(), name
    for attribute in ("rate_hz", "delay_frames", "n_modes", "soulctl_version", "diverged_at", "configuration"):
        assert attribute in doc and TELEMETRY_SCHEMA[attribute].where == "attribute"


def test_a_valid_file_reads_back(h5):
    data, attrs = read_telemetry(h5)
    assert data["measured_modes"].dtype == np.float32 and data["gain_history/frames"].tolist() == [0, 10]
    assert np.isnan(data["aux/ogtl/optical_gain"][0])
    assert attrs["rate_hz"] == 400.0 and attrs["configuration"] == {"oversampling": 1} and attrs["diverged_at"] == -1
    with TelemetryReader(h5) as tm:
        assert tm.dims["frames"][0] == FRAMES and tm.dim("n_modes") == MODES and tm.dim("changes") == 2
        np.testing.assert_array_equal(tm.read("measured_modes", slice(30, 40), slice(1, 3)), data["measured_modes"][30:, 1:])


@pytest.mark.parametrize(
    "change, message",
    [
        (replace("measured_modes", np.array([["a"] * MODES] * FRAMES, dtype="S1")), "field measured_modes holds text"),
        (replace("measured_modes", np.ones((FRAMES, MODES), dtype=complex)), "field measured_modes holds complex numbers"),
        (replace("gains", np.ones(MODES, dtype=bool)), "field gains holds booleans"),
        (lambda f: (f.__delitem__("gains"), f.create_group("gains")), "field gains is a group, expected a dataset"),
        (lambda f: (f.__delitem__("gain_history"), f.__setitem__("gain_history", [1.0])), "gain_history is a dataset, expected a group"),
        (replace("sensitivity", np.ones((FRAMES, 1))), "field sensitivity has shape (40, 1), expected (frames,)"),
        (replace("command_modes", np.ones((FRAMES - 1, MODES))), "field command_modes has 39 frames, measured_modes has 40"),
        (replace("gains", np.ones(MODES + 1)), "field gains has 4 modes, measured_modes has 3"),
        (replace("gain_history/gains", np.ones((3, MODES))), "field gain_history/gains has 3 entries, gain_history/frames has 2"),
        (
            replace("gain_history/frames", np.zeros((2, 1), dtype=np.int64)),
            "field gain_history/frames has shape (2, 1), expected (changes,)",
        ),
        (lambda f: f["gain_history"].__delitem__("gains"), "gain_history needs both frames and gains"),
        (lambda f: f.attrs.__setitem__("rate_hz", "fast"), "attribute rate_hz must be a number in 0..100000 Hz (> 0), got 'fast'"),
        (
            lambda f: f.attrs.__setitem__("rate_hz", [400.0, 400.0]),
            "attribute rate_hz must be a number in 0..100000 Hz (> 0), got an array of shape (2,)",
        ),
        (lambda f: f.attrs.__setitem__("rate_hz", np.nan), "attribute rate_hz must be a number in 0..100000 Hz (> 0), got nan"),
        (
            lambda f: f.attrs.__setitem__("rate_hz", 1 + 2j),
            "attribute rate_hz must be a number in 0..100000 Hz (> 0), got the complex number",
        ),
        (lambda f: f.attrs.__setitem__("delay_frames", -1.0), "attribute delay_frames must be a number in 0..50 frames, got -1"),
        (lambda f: f.attrs.__setitem__("diverged_at", 2.5), "attribute diverged_at must be an integer in -1..2^63-1, got 2.5"),
        (lambda f: f.attrs.__setitem__("diverged_at", 41), "attribute diverged_at is 41, beyond the file's 40 frames"),
        (lambda f: f.attrs.__setitem__("n_modes", 4), "attribute n_modes is 4, measured_modes has 3 modes"),
        (lambda f: f.attrs.__setitem__("configuration", np.bytes_(b"\xff")), "attribute configuration is not UTF-8 text"),
        (lambda f: f.attrs.__setitem__("configuration", "[1, 2]"), "attribute configuration must be a JSON object"),
        (lambda f: f.attrs.__setitem__("configuration", "[" * 5000), "attribute configuration is not JSON"),
        (lambda f: f.attrs.__setitem__("configuration", 3.0), "attribute configuration must be text, got 3"),
        (lambda f: f["aux"].create_dataset("x", data=[1.0]), "aux/x is a dataset, expected a group"),
        (lambda f: f["aux/ogtl"].create_dataset("label", data=[b"x"]), "field aux/ogtl/label holds text"),
        (lambda f: f["aux/ogtl"].create_dataset("chi", data=[1.0, 2.0]), "aux/ogtl/chi has 2: the fields must agree"),
        (lambda f: f.__setitem__("gain_history/elsewhere", h5py.ExternalLink("/dev/zero", "/")), None),
        (replace("measured_modes", h5py.ExternalLink("other.h5", "/data")), "measured_modes is a link to another file"),
    ],
)
def test_layout_errors_name_the_field(h5, change, message):
    edit(h5, change)
    if message is None:  # an unknown member: not read, not an error
        read_telemetry(h5)
        return
    for reader in (read_telemetry, lambda p: TelemetryReader(p).close()):
        with pytest.raises(InputError, match=re.escape(message)):
            reader(h5)


@pytest.mark.parametrize(
    "change, message",
    [
        (lambda f: f["measured_modes"].__setitem__((3, 1), np.nan), "field measured_modes has 1 NaN or infinite values"),
        (
            lambda f: f["command_modes"].__setitem__((3, 1), 1e7),
            "field command_modes must hold real numbers in -1000000..1000000 nm, got 10000000",
        ),
        (lambda f: f["gains"].__setitem__(0, -0.5), "field gains must hold real numbers in 0..10, got -0.5"),
        (
            lambda f: f["gain_history/gains"].__setitem__((0, 0), 4e5),
            "field gain_history/gains must hold real numbers in 0..10, got 400000",
        ),
        (lambda f: f["sensitivity"].__setitem__(5, 0.0), "field sensitivity must hold real numbers in 0.05..20, got 0"),
        (replace("gain_history/frames", np.array([-5, 10])), "field gain_history/frames must hold integers in 0..2^63-1, got -5"),
        (
            replace("gain_history/frames", np.array([0, 10**12])),
            "field gain_history/frames holds frame 1000000000000, beyond the file's 40 frames",
        ),
        (replace("gain_history/frames", np.array([10, 0])), "field gain_history/frames must increase strictly"),
        (replace("gain_history/frames", np.array([0.0, 2.5])), "field gain_history/frames must hold integers in 0..2^63-1, got 2.5"),
        (replace("gain_history/frames", np.array([0, 2**64 - 1], dtype=np.uint64)), "got 18446744073709551615"),
    ],
)
def test_value_errors_name_the_field(h5, change, message):
    edit(h5, change)
    with pytest.raises(InputError, match=re.escape(message)):
        read_telemetry(h5)


def test_a_diverged_loop_may_record_anything_from_the_frame_it_diverged_at(h5):
    def diverged(f):
        f.attrs["diverged_at"] = 38
        f["measured_modes"][38:] = np.inf
        f["residual_rms_nm"][39] = np.nan

    edit(h5, diverged)
    data, attrs = read_telemetry(h5)
    assert attrs["diverged_at"] == 38 and np.isinf(data["measured_modes"][38:]).all()
    edit(h5, lambda f: f["measured_modes"].__setitem__((37, 0), np.nan))
    with pytest.raises(InputError, match="field measured_modes has 1 NaN"):
        read_telemetry(h5)


def test_only_regular_hdf5_files_are_read(tmp_path):
    text = tmp_path / "notes.h5"
    text.write_text("not HDF5\n")
    for path, message in ((text, "is not an HDF5 file"), (tmp_path, "is a directory"), (tmp_path / "none.h5", "not found")):
        with pytest.raises(InputError, match=message):
            read_telemetry(path)
    fifo = tmp_path / "fifo.h5"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="is a FIFO"):
        read_telemetry(fifo)
    truncated = tmp_path / "cut.h5"
    full = tmp_path / "full.h5"
    write_telemetry(full, arrays(), {"rate_hz": 400.0, "delay_frames": 1.5}, {})
    truncated.write_bytes(full.read_bytes()[:3000])
    with pytest.raises(InputError, match="cut.h5"):
        read_telemetry(truncated)


def test_missing_fields_are_named(h5):
    edit(h5, lambda f: (f.__delitem__("command_modes"), f.attrs.__delitem__("rate_hz")))
    with pytest.raises(InputError, match="lacks command_modes, rate_hz"):
        read_telemetry(h5)
