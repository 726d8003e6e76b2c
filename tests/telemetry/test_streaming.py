"""Telemetry streamed to disk at constant memory: what the recorder keeps, what the HDF5 writer
writes (decimation, fields, units), and the files an interrupted, diverged or killed run leaves."""

import shutil
import signal
import subprocess
import time
import tracemalloc

import h5py
import numpy as np
import pytest
from cheap import CHEAP_PYRAMID

from soulctl.cli.app import main
from soulctl.control.gains import LoopGains
from soulctl.loop import simulation
from soulctl.loop.auxloop import AuxLoop
from soulctl.loop.run import RunRequest, calibration_for
from soulctl.loop.simulation import ClosedLoop
from soulctl.observation import observation_for_magnitude
from soulctl.optics.atmosphere import AtmosphereConfig
from soulctl.telemetry.recorder import MemorySink, ModalMoments, Ring, Series
from soulctl.telemetry.schema import DEFAULT_FIELDS, TelemetryReader

OBS = observation_for_magnitude(16.5)  # 90 modes, 250 Hz, 288 slopes: a fast loop
SMALL = ["--mag", "16.5", *CHEAP_PYRAMID]


class Reader(AuxLoop):
    """An auxiliary loop that reads its window and records its size."""

    name = "reader"

    def update(self, window, rtc):
        return {"rows": float(window.frames)}


@pytest.fixture(scope="module")
def calibration(optics_cache):
    return calibration_for(RunRequest(observation=OBS, oversampling=1, wfs_field_arcsec=0.0), optics_cache)


def test_ring_series_and_moments_hold_what_numpy_computes():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(700, 5))
    ring, series, moments = Ring(x[0], 64), Series(5), ModalMoments(start=100)
    for k, row in enumerate(x):
        ring.put(k, row)
        series.append(row)
        moments.add(k, row)
    np.testing.assert_array_equal(ring.rows(650, 700), x[650:])
    np.testing.assert_array_equal(ring.resized(128, 700).rows(640, 700), x[640:])
    np.testing.assert_array_equal(series.values, x)
    np.testing.assert_allclose(moments.variance, x[100:].var(axis=0), rtol=1e-12)


def test_the_recorder_keeps_only_the_windows_and_the_metrics_series(calibration):
    """Rows kept per window field = the longest auxiliary period, whatever the run's length;
    the metrics series and moments equal what the whole record gives."""
    sink = MemorySink()
    loop = ClosedLoop(OBS, calibration, AtmosphereConfig.lbt_default(1.0), LoopGains(0.3, 0.3, 0.3), structure=None, sink=sink)
    loop.telemetry.moments_from(50)
    loop.add_aux_loop(Reader(25))
    loop.run(300)
    tm, whole = loop.telemetry, sink.arrays()
    assert tm.window_frames == 25 and all(ring._data.shape[0] == 25 for ring in tm._rings.values())
    assert tm.aux_arrays("reader")["rows"].max() == 25
    np.testing.assert_array_equal(tm.series("residual_tt"), whole["residual_modes"][:, :2])
    np.testing.assert_array_equal(tm.series("command_tt"), whole["command_modes"][:, :2])
    np.testing.assert_allclose(tm.residual_moments.variance, whole["residual_modes"][50:].var(axis=0), rtol=1e-9)
    np.testing.assert_array_equal(loop.window(25).measured_modes, whole["measured_modes"][-25:])


def _grown_per_frame(calibration, frames: int) -> float:
    loop = ClosedLoop(OBS, calibration, AtmosphereConfig.lbt_default(1.0), LoopGains(0.3, 0.3, 0.3), structure=None)
    loop.add_aux_loop(Reader(50))
    loop.run(60)
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    loop.run(frames)
    grown = tracemalloc.get_traced_memory()[0] - before
    tracemalloc.stop()
    return grown / frames


def test_memory_does_not_grow_with_the_run(calibration):
    """The constant-memory property: what a frame leaves behind is the metrics series' 72
    bytes (plus the doubling of their arrays), not its records (~7 kB here: 288 slopes, 672
    commands, 5 x 90 modes)."""
    per_frame = _grown_per_frame(calibration, 900)
    assert per_frame < 200, per_frame


def test_the_stream_records_the_chosen_fields_one_frame_in_n(tmp_path, capsys, optics_cache):
    h5 = tmp_path / "t.h5"
    argv = ["loop", "run", *SMALL, "--duration", "0.6", "--telemetry", str(h5), "--telemetry-every", "3"]
    assert main([*argv, "--cache-dir", str(optics_cache.directory), "--json"]) == 0
    with h5py.File(h5) as f:
        assert f.attrs["status"] == "complete" and f.attrs["schema_version"] == 2 and f.attrs["telemetry_every"] == 3
        assert set(DEFAULT_FIELDS) <= set(f) and "slopes" not in f and "commands" not in f
        np.testing.assert_array_equal(f["frame_counter"][:], np.arange(0, 150, 3))
        np.testing.assert_allclose(f["frame_time_s"][:], np.arange(0, 150, 3) / 250.0)
        assert f["measured_modes"].attrs["unit"] == "nm" and f["flux"].attrs["unit"] == "electron"
        assert f["reconstructor"].shape == (90, 288) and f["modes_to_commands"].shape == (672, 90)
    capsys.readouterr()
    status = main(["optimize", "gains", "--method", "mgm", "--telemetry", str(h5), "--cache-dir", str(optics_cache.directory)])
    err = capsys.readouterr().err
    assert status == 2 and "frame_counter steps by 3" in err and err.count("\n") == 1
    status = main(["loop", "run", *SMALL, "--telemetry", str(tmp_path / "x.h5"), "--telemetry-fields", "slopes,wind"])
    err = capsys.readouterr().err
    assert status == 2 and "unknown field wind" in err and not (tmp_path / "x.h5").exists()


def _interrupt_at(monkeypatch, frame: int, exception):
    step = simulation.ClosedLoop.step

    def interrupted(self):
        if self.frame == frame:
            raise exception
        return step(self)

    monkeypatch.setattr(simulation.ClosedLoop, "step", interrupted)


def test_an_interrupted_run_leaves_a_partial_file_with_every_frame_so_far(tmp_path, capsys, monkeypatch, optics_cache):
    from soulctl.cli.app import Interrupted

    h5 = tmp_path / "t.h5"
    _interrupt_at(monkeypatch, 300, Interrupted(signal.SIGTERM))
    argv = ["loop", "run", *SMALL, "--duration", "2", "--telemetry", str(h5), "--cache-dir", str(optics_cache.directory)]
    assert main(argv) == 143
    with TelemetryReader(h5) as tm:
        assert tm.attribute("status") == "partial" and tm.attribute("partial_reason") == "interrupted by SIGTERM"
        assert tm.dim("frames") == 300 and tm.read("frame_counter")[-1] == 299
    assert [p.name for p in tmp_path.iterdir()] == ["t.h5"]  # no temporary left


def test_a_diverged_run_is_partial_with_its_reason(tmp_path, capsys, monkeypatch, optics_cache):
    h5 = tmp_path / "t.h5"
    _interrupt_at(monkeypatch, 120, simulation.LoopDiverged(120, 1e4))
    argv = ["loop", "run", *SMALL, "--duration", "1", "--telemetry", str(h5), "--cache-dir", str(optics_cache.directory)]
    assert main(argv) == 3
    with h5py.File(h5) as f:
        assert f.attrs["status"] == "partial" and f.attrs["partial_reason"] == "the loop diverged at frame 120"
        assert f.attrs["diverged_at"] == 120 and f["frame_counter"].shape == (120,)


def test_a_killed_run_never_leaves_a_file_that_reads_as_complete(tmp_path, optics_cache):
    """SIGKILL: no clean-up runs.  The target is not created; the temporary holds the flushed
    chunks and says 'writing'."""
    h5 = tmp_path / "t.h5"
    # low gains: SMALL's default gains diverge at frame 469 (oversampling 1), which ended the run
    # before the poll saw the temporary when the machine was loaded
    cmd = [shutil.which("soulctl"), "loop", "run", *SMALL, "--gains", "0.3,0.2,0.1", "--duration", "30", "--telemetry", str(h5)]
    # cwd: the installed package, never a source tree's soulctl/ (which has no compiled core)
    cache = ["--cache-dir", str(optics_cache.directory)]
    proc = subprocess.Popen([*cmd, *cache], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=tmp_path)
    deadline = time.monotonic() + 120
    temps: list = []
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            temps = list(tmp_path.glob(".soulctl-*.tmp.h5"))
            if temps and _flushed(temps[0]) >= 256:
                break
            time.sleep(0.5)
    finally:
        proc.send_signal(signal.SIGKILL)
        _, err = proc.communicate()
    assert temps, f"no temporary file appeared (exit {proc.returncode}): {err.decode()[-300:]}"
    assert not h5.exists()
    with TelemetryReader(temps[0], required=()) as tm:
        assert tm.attribute("status") == "writing" and tm.dim("frames") % 256 == 0 and tm.dim("frames") >= 256


def _flushed(path) -> int:
    try:
        with h5py.File(path, "r", locking=False) as f:  # the writer holds the file's lock
            return f["frame_counter"].shape[0] if "frame_counter" in f else 0
    except (OSError, RuntimeError):  # read while the writer extends it: h5py may see a half-written block
        return 0


def test_files_of_an_earlier_schema_are_read_and_a_later_one_is_refused(tmp_path, capsys):
    old = tmp_path / "v1.h5"
    with h5py.File(old, "w") as f:  # soulctl before streaming: no schema_version, frame_counter or status
        f["measured_modes"] = np.zeros((40, 3), dtype=np.float32)
        f["command_modes"] = np.zeros((40, 3), dtype=np.float32)
        f["gains"] = np.full(3, 0.3)
        f.attrs.update({"rate_hz": 250.0, "delay_frames": 1.5, "n_modes": 3})
    with TelemetryReader(old) as tm:
        assert tm.dim("frames") == 40 and tm.attribute("schema_version", 1) == 1
    newer = tmp_path / "v3.h5"
    shutil.copy(old, newer)
    with h5py.File(newer, "r+") as f:
        f.attrs["schema_version"] = 3
    assert main(["telemetry", "inspect", str(newer)]) == 2
    assert "schema version 3 is newer than this soulctl reads (1..2)" in capsys.readouterr().err


def test_spectra_of_a_diverged_record_use_the_frames_before_it(tmp_path, capsys, monkeypatch, optics_cache):
    """A partial file of a diverged loop: `telemetry psd` reads the frames before the
    divergence (the frame it diverged at holds anything) and prints finite JSON."""
    h5 = tmp_path / "t.h5"
    step = simulation.ClosedLoop.step

    def blows_up(self):
        residual = step(self)
        if self.frame == 200:
            self.telemetry.sink._buffers["measured_modes"][self.telemetry.sink._buffered - 1] = np.inf
            raise simulation.LoopDiverged(199, 1e4)
        return residual

    monkeypatch.setattr(simulation.ClosedLoop, "step", blows_up)
    argv = ["loop", "run", *SMALL, "--duration", "1", "--telemetry", str(h5), "--cache-dir", str(optics_cache.directory)]
    assert main(argv) == 3
    capsys.readouterr()
    assert main(["telemetry", "psd", str(h5), "--pseudo-open-loop", "--json"]) == 0
    out = capsys.readouterr().out
    assert "NaN" not in out and "Infinity" not in out
