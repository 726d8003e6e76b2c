"""The files soulctl writes and reads, for every command: never a device, FIFO, socket,
directory or read-only file replaced; symlinks written through; an output that is an input
refused before any work; unwritable locations found up front; an error or an interrupt leaves
no output and no temporary; inputs read only if they are regular files of bounded size."""

import json
import os
import shutil
import signal
import socket
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
from cheap import CHEAP_PYRAMID
from cli_run import run

from soulctl.cli.app import main

# (arguments, output option) for every option that writes a file; each refusal below happens
# before any work, so the expensive commands are as quick to test as the cheap ones.
WRITERS = [
    (["configure", "--mag", "12"], "--out"),
    (["filter", "analyze", "--rate", "1000", "--gain", "0.3"], "--plot"),
    (["filter", "design", "--rate", "1700"], "--out"),
    (["filter", "design", "--rate", "1700"], "--plot"),
    (["optics", "gains", "--binning", "4", *CHEAP_PYRAMID], "--out"),
    (["loop", "run", "--mag", "16.5", *CHEAP_PYRAMID], "--telemetry"),
    (["optimize", "gains", "--mag", "16.5", *CHEAP_PYRAMID], "--out"),
]


def suffix(option: str, args: list) -> str:
    return {"--telemetry": ".h5", "--plot": ".png", "--out": ".csv" if args[0] in ("filter", "optics") else ".toml"}[option]


def special_targets(tmp_path: Path) -> dict[str, Path]:
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    sock = tmp_path / "sock"
    s = socket.socket(socket.AF_UNIX)
    s.bind(str(sock))
    s.close()
    folder = tmp_path / "folder.out"
    folder.mkdir()
    return {"character device": Path("/dev/null"), "FIFO": fifo, "socket": sock, "directory": folder}


@pytest.mark.parametrize("args, option", WRITERS)
def test_outputs_never_replace_special_files(args, option, tmp_path, capsys):
    for kind, target in special_targets(tmp_path).items():
        mode = os.stat(target).st_mode
        status, out, err = run([*args, option, target], capsys)
        assert status == 2, (kind, err)
        assert err.count("\n") == 1 and "soulctl writes only regular files" in err
        assert os.stat(target).st_mode == mode, f"{target} was replaced"
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


@pytest.mark.parametrize("args, option", WRITERS)
def test_read_only_outputs_are_refused_and_kept(args, option, tmp_path, capsys):
    target = tmp_path / ("kept" + suffix(option, args))
    target.write_text("precious")
    target.chmod(0o444)
    status, _, err = run([*args, option, target], capsys)
    assert status == 2 and "read-only" in err and err.count("\n") == 1
    assert target.read_text() == "precious" and stat.S_IMODE(target.stat().st_mode) == 0o444


@pytest.mark.parametrize("args, option", WRITERS)
def test_unwritable_locations_are_found_up_front(args, option, tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    for target in (
        a_file / ("under" + suffix(option, args)),
        Path("/proc/soulctl-cannot" + suffix(option, args)),
        tmp_path / "missing" / ("x" + suffix(option, args)),
    ):
        t0 = time.perf_counter()
        status, _, err = run([*args, option, target], capsys)
        assert status == 2 and "cannot write" in err and err.count("\n") == 1, err
        assert time.perf_counter() - t0 < 5, "refused only after the work"


def test_symlinks_are_written_through_and_modes_kept(tmp_path, capsys):
    target = tmp_path / "real.toml"
    target.write_text("old")
    target.chmod(0o600)
    link = tmp_path / "link.toml"
    link.symlink_to(target)
    status, _, err = run(["configure", "--mag", "12", "--out", link], capsys)
    assert status == 0, err
    assert link.is_symlink() and "[wfs]" in target.read_text()
    assert stat.S_IMODE(target.stat().st_mode) == 0o600


@pytest.mark.parametrize(
    "args",
    [
        ["loop", "run", "--config", "{obs}", "--telemetry", "{obs}"],
        ["optimize", "gains", "--telemetry", "{h5}", "--out", "{h5}"],
        ["configure", "--mag", "9.7", "--roots", "{roots}", "--out", "{roots}"],
        ["filter", "design", "--rate", "1700", "--vibrations", "{vib}", "--out", "{vib}"],
        ["loop", "run", "--config", "{obs}", "--telemetry", "{link}"],
    ],
)
def test_an_output_that_is_an_input_is_refused_before_any_work(args, tmp_path, capsys):
    files = {
        "obs": tmp_path / "obs.toml",
        "h5": tmp_path / "t.h5",
        "roots": tmp_path / "roots.csv",
        "vib": tmp_path / "vib.toml",
        "link": tmp_path / "link.h5",
    }
    assert main(["configure", "--mag", "16.5", "--out", str(files["obs"])]) == 0
    files["h5"].write_bytes(b"HDF5 stand-in")
    files["roots"].write_text("frame_rate_hz,zero1,zero2,zero3,zero4,pole1,pole2,pole3,pole4\n1700,0,0,0,0,0,0,0,1\n")
    files["vib"].write_text("[[line]]\nfrequency_hz = 13.0\ndamping = 0.02\ntip_mas = 9.0\ntilt_mas = 6.5\n")
    files["link"].symlink_to(files["obs"])
    before = {k: p.read_bytes() for k, p in files.items()}
    capsys.readouterr()
    status, _, err = run([a.format(**{k: str(p) for k, p in files.items()}) for a in args], capsys)
    assert status == 2 and "is also the input" in err and err.count("\n") == 1
    assert {k: p.read_bytes() for k, p in files.items()} == before


def no_new_files(folder: Path, before: set) -> list:
    return sorted(p.name for p in folder.iterdir() if p.name not in before)


def _short_loop(tmp_path: Path, plot: Path) -> list:
    return [
        "loop",
        "run",
        "--mag",
        "16.5",
        *CHEAP_PYRAMID,
        "--duration",
        "0.05",
        "--telemetry",
        tmp_path / "ok.h5",
        "--plot",
        plot,
        "--cache-dir",
        tmp_path / "cache",
    ]


def test_a_plot_folder_is_created_with_its_parents(tmp_path, capsys):
    from soulctl.plots.loop import LOOP_FIGURES

    plot = tmp_path / "figures" / "run1"
    status, _, err = run(_short_loop(tmp_path, plot), capsys)
    assert status == 0, err
    names = {p.name for p in plot.iterdir()}
    assert "modal_variance.png" in names and names <= set(LOOP_FIGURES)  # 12 frames: a loop not settled, no PSF


@pytest.mark.slow
@pytest.mark.parametrize("failure, status", [(RuntimeError("a late bug"), 1), ("input", 2)])
def test_a_failing_command_leaves_no_output(failure, status, tmp_path, capsys, monkeypatch):
    """The telemetry is written, then the figures fail: nothing lands, no temporary stays, and
    the folder made for the figures is gone again."""
    from soulctl.errors import InputError
    from soulctl.plots import loop as loop_plots  # `loop run` imports its figures when it draws them

    def fail(*_):
        raise InputError("the figures could not be made") if failure == "input" else failure

    monkeypatch.setattr(loop_plots, "write_loop_figures", fail)
    before = set(os.listdir(tmp_path))
    args = _short_loop(tmp_path, tmp_path / "figures" / "run1")
    if status == 1:
        with pytest.raises(RuntimeError):
            main([str(a) for a in args])
    else:
        assert run(args, capsys)[0] == 2
    assert no_new_files(tmp_path, before | {"cache"}) == []


INTERRUPTED = """
import os, sys, time
from soulctl.cli import app
from soulctl.plots import loop as loop_plots
def slow(*args):
    open(os.environ["SOULCTL_TEST_READY"], "w").close()
    time.sleep(60)
loop_plots.write_loop_figures = slow
sys.exit(app.main(sys.argv[1:]))
"""


@pytest.mark.slow
@pytest.mark.parametrize("signum, status, word", [(signal.SIGTERM, 143, "SIGTERM"), (signal.SIGINT, 130, "Ctrl-C")])
def test_an_interrupt_removes_the_temporaries_and_says_so(signum, status, word, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    args = [
        "loop",
        "run",
        "--mag",
        "16.5",
        *CHEAP_PYRAMID,
        "--duration",
        "0.05",
        "--telemetry",
        out / "tm.h5",
        "--plot",
        out,
        "--cache-dir",
        tmp_path / "cache",
    ]
    # run from tmp_path: `python -c` puts the current folder first on sys.path, and the
    # installed package (with its compiled core) must be the one imported
    # the signal comes while the figures are made, the telemetry's temporary written: not
    # inside h5py's writing, where a signal lands in a weakref callback and is dropped by
    # Python (then `_Signals.check` raises it again once the command has finished)
    ready = tmp_path / "ready"
    env = {**os.environ, "SOULCTL_TEST_READY": str(ready)}
    p = subprocess.Popen(
        [sys.executable, "-c", INTERRUPTED, *map(str, args)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=tmp_path,
        env=env,
    )
    deadline = time.time() + 120
    while not ready.exists():
        assert p.poll() is None and time.time() < deadline, p.communicate()
        time.sleep(0.05)
    assert any(f.name.startswith(".soulctl-") for f in out.iterdir())
    p.send_signal(signum)
    _, err = p.communicate(timeout=30)
    assert p.returncode == status
    assert err.strip().count("\n") == 0 and word in err and "Traceback" not in err
    assert list(out.iterdir()) == []


# --------------------------------------------------------------------------------- inputs

INPUTS = [
    ["loop", "run", "--config", "{}"],
    ["loop", "run", "--mag", "16.5", "--vibrations", "{}"],
    ["loop", "run", "--mag", "16.5", "--gains", "{}"],
    ["configure", "--mag", "12", "--roots", "{}"],
    ["filter", "design", "--rate", "1700", "--vibrations", "{}"],
    ["optics", "calibrate", "--config", "{}"],
    ["optimize", "gains", "--telemetry", "{}"],
    ["telemetry", "inspect", "{}"],
    ["telemetry", "psd", "{}"],
    ["telemetry", "convert", "{}", "out.h5"],
    ["sweep", "{}"],
]
TELEMETRY_FOLDER = "an LBT tracking-number folder holds one FramesCounter_<TN>.fits"  # a folder is telemetry (also as --config)


@pytest.mark.parametrize("args", INPUTS)
def test_inputs_must_be_regular_files(args, tmp_path, capsys):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)  # opening it would block forever
    for source in ("/dev/zero", str(fifo), str(tmp_path)):
        t0 = time.perf_counter()
        status, out, err = run([a.format(source) for a in args], capsys)
        assert status == 2 and err.count("\n") == 1, err
        folder_read = source == str(tmp_path) and (any("telemetry" in a for a in args) or "--config" in args)
        assert "regular files only" in err or "must be" in err or (folder_read and TELEMETRY_FOLDER in err), err
        assert time.perf_counter() - t0 < 5


@pytest.mark.parametrize("args", [a for a in INPUTS if "--telemetry" not in a and a[0] != "telemetry"])
def test_text_inputs_are_capped(args, tmp_path, capsys):
    big = tmp_path / "big.toml"
    with open(big, "wb") as f:
        f.truncate(17 * 2**20)
    status, _, err = run([a.format(big) for a in args], capsys)
    assert status == 2 and "more than the 16 MB accepted" in err


def test_readme_roots_example_and_user_paths_are_relative_to_the_current_folder(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    # the README's example, with one rate to keep it short
    assert main(["filter", "design", "--rate", "1700", "--out", "roots.csv"]) == 0
    status, out, err = run(["configure", "--mag", "9.7", "--roots", "roots.csv", "--json"], capsys)
    assert status == 0, err
    # a user file named like the built-in table is the user's
    Path("tt_iir_roots.csv").write_text(
        "frame_rate_hz,zero1,zero2,zero3,zero4,pole1,pole2,pole3,pole4\n1700,0.1,0.2,0.3,0.4,0.0,0.0,0.5,1\n"
    )
    status, out, err = run(["configure", "--mag", "9.7", "--roots", "tt_iir_roots.csv", "--json"], capsys)
    assert status == 0, err
    assert json.loads(out)["control"]["tt_zeros"] == [0.1, 0.2, 0.3, 0.4]


# --------------------------------------------------------------------------- what is printed


@pytest.mark.parametrize("text", ["[/]", "[bold]x[/bold]", "[red", ":smile:", "\\[x]"])
def test_user_text_prints_as_given(text, tmp_path, capsys):
    plot = tmp_path / f"{text.replace('/', '_')}.png"
    status, out, err = run(["filter", "analyze", "--rate", "1000", "--gain", "0.3", "--label", text, "--plot", plot], capsys)
    assert status == 0, err
    assert text in out and f"written {plot}" in out


@pytest.mark.parametrize(
    "args",
    [
        ["configure", "--mag", "13"],
        ["filter", "analyze", "--rate", "1700", "--control", "leaky", "--gain", "0.3"],
        ["optics", "atmosphere"],
        ["configure", "--mag", "99"],
    ],
)
def test_a_terminal_without_utf8_gets_ascii(args, tmp_path):
    p = subprocess.run(
        [shutil.which("soulctl"), *args],
        capture_output=True,
        cwd=tmp_path,
        env={**os.environ, "PYTHONIOENCODING": "ascii", "LC_ALL": "C"},
        timeout=60,
    )
    assert p.returncode in (0, 2), p.stderr
    assert b"Traceback" not in p.stderr
    p.stdout.decode("ascii")
    if args[-1] == "13":
        assert b"lambda/D" in p.stdout


def test_a_signal_lost_in_a_finaliser_still_discards_the_outputs(tmp_path, capsys, monkeypatch):
    """Python prints and drops an exception raised in a finaliser or weakref callback (h5py
    closing a file): the signal is remembered and nothing is committed."""
    from soulctl.plots import loop as loop_plots

    def swallowed(*_):
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.1)  # the handler runs here, and its exception is dropped below
        except BaseException:  # noqa: BLE001 - as a finaliser would
            pass

    monkeypatch.setattr(loop_plots, "write_loop_figures", swallowed)
    args = [
        "loop",
        "run",
        "--mag",
        "16.5",
        *CHEAP_PYRAMID,
        "--duration",
        "0.05",
        "--telemetry",
        tmp_path / "tm.h5",
        "--plot",
        tmp_path,
        "--cache-dir",
        tmp_path / "cache",
    ]
    status, out, err = run(args, capsys)
    assert status == 143 and "interrupted (SIGTERM)" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cache"]


def test_a_reader_that_goes_away_keeps_the_outputs(tmp_path):
    p = subprocess.Popen(
        [
            shutil.which("soulctl"),
            "loop",
            "run",
            "--mag",
            "16.5",
            *CHEAP_PYRAMID,
            "--duration",
            "0.05",
            "--telemetry",
            str(tmp_path / "tm.h5"),
            "--cache-dir",
            str(tmp_path / "cache"),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        cwd=tmp_path,
    )
    p.stdout.close()  # the reader goes away before the table is written (`| head -c 0`): no race with its writes
    _, err = p.communicate(timeout=120)
    assert p.returncode == 141 and err == b""
    assert (tmp_path / "tm.h5").stat().st_size > 0


def test_an_unwritable_cache_home_keeps_refusals_to_one_line(tmp_path):
    env = {**os.environ, "XDG_CACHE_HOME": "/proc/soulctl-no-cache", "MPLCONFIGDIR": "/proc/soulctl-no-mpl"}
    p = subprocess.run([shutil.which("soulctl"), "configure", "--mag", "19"], capture_output=True, env=env, cwd=tmp_path, timeout=60)
    assert p.returncode == 2 and p.stderr.count(b"\n") == 1 and p.stdout == b""


def test_ascii_tables_are_measured_on_what_is_printed(tmp_path):
    p = subprocess.run(
        [shutil.which("soulctl"), "filter", "analyze", "--rate", "1000", "--gain", "0.5", "--label", "λ☃日本"],
        capture_output=True,
        env={**os.environ, "PYTHONIOENCODING": "ascii"},
        cwd=tmp_path,
        timeout=60,
    )
    assert p.returncode == 0
    rows = [line for line in p.stdout.decode("ascii").splitlines() if line.startswith(("|", "+"))]
    assert len(rows) > 10 and len({len(line) for line in rows}) == 1


@pytest.mark.parametrize("label", ["$x^{$", "a$b$,$\\alpha$"])
def test_labels_are_not_matplotlib_math(label, tmp_path, capsys):
    status, out, err = run(["filter", "analyze", "--rate", "1000", "--gain", "0.5", "--label", label, "--plot", tmp_path / "l.png"], capsys)
    assert status == 0, err
    assert (tmp_path / "l.png").read_bytes()[:4] == b"\x89PNG"


def test_overlong_labels_are_refused(capsys):
    status, _, err = run(["filter", "analyze", "--rate", "1000", "--gain", "0.5", "--label", "x" * 81], capsys)
    assert status == 2 and "at most 80 characters" in err


def test_figures_draw_user_text_as_given_and_log_ticks_as_powers(tmp_path):
    """save_figure turns math off for the figure's text (a '$' in a label is a dollar) but not
    for the tick labels the formatters make: 10^k on a log axis is drawn as a power, not as
    the raw '$\\mathdefault{10^{1}}$'."""
    from soulctl.plots.figure import new_figure, save_figure

    fig = new_figure()
    ax = fig.subplots()
    ax.loglog([1, 10, 100], [1, 10, 100])
    label = ax.set_title("cost $5 per $10")
    save_figure(fig, tmp_path / "f.png")
    assert not label.get_parse_math()
    ticks = [t for t in ax.get_xticklabels() if t.get_text()]
    assert ticks and all(t.get_parse_math() and "mathdefault" in t.get_text() for t in ticks)
