"""The command-line contract, property-based: every command's numeric options driven with
arbitrary floats, integers and strings.  Whatever the value:

* the exit status is 0, 2 or 3, never 1 (a bug) and never a traceback;
* on exit 2, stderr is one line and stdout is empty;
* with --json, stdout is one valid JSON object without NaN or Infinity tokens;
* the command returns within a bound of CPU time (the case's limit; ``time_limit``).

Each option is fuzzed alone, the others at a small, fast configuration.  The options that set
the amount of work (--duration, --measure, --screens, ...) draw their accepted values from the
small end of their range: every other value is drawn from the whole line.

CI runs a few examples per option (profile "soulctl-ci"); for many, run
    HYPOTHESIS_PROFILE=soulctl-thorough pytest tests/cli/test_properties.py
"""

import contextlib
import io
import json
import os
import signal
import time

import pytest
from cheap import CHEAP_PYRAMID
from foreign_records import tip_tilt_loop, write_aot
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from lbt_layout import write_real_folder

from soulctl.cli.app import main

settings.register_profile(
    "soulctl-ci",
    max_examples=6,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)
settings.register_profile(
    "soulctl-thorough", max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture]
)
PROFILE = settings.get_profile(
    os.environ.get("HYPOTHESIS_PROFILE", "soulctl-ci") if os.environ.get("HYPOTHESIS_PROFILE", "").startswith("soulctl-") else "soulctl-ci"
)

SPECIAL = [
    "nan",
    "inf",
    "-inf",
    "-0",
    "0",
    "1",
    "0.5",
    "-1",
    "1e308",
    "1e-300",
    "5e-324",
    "",
    " ",
    "abc",
    "1,2",
    "1_0",
    "0x10",
    "１２",
    "١٢",
    "1e999",
    "2" * 40,
    "None",
    "true",
    "[]",
]
NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(min_value=-(10**30), max_value=10**30).map(str),
    st.sampled_from(SPECIAL),
    st.text(max_size=6),
)
LISTS = st.lists(NUMBERS, min_size=1, max_size=4).map(",".join)
CHOICES = st.one_of(st.sampled_from(["auto", "lbt", "none"]), st.text(max_size=6), st.sampled_from(SPECIAL))  # --resonance
# --misregistration: anything, or an accepted DX,DY,ROT,MAG (the verdict's JSON, inf margins included)
REGISTRATIONS = st.one_of(
    st.tuples(st.floats(-2, 2), st.floats(-2, 2), st.floats(-10, 10), st.floats(0.8, 1.2)).map(lambda t: ",".join(map(repr, t))),
    LISTS,
)


def small(hi: float) -> st.SearchStrategy:
    """Values of an option that sets the amount of work: anything outside (0, hi], or a small
    accepted value."""
    return st.one_of(NUMBERS.filter(lambda t: not _in(t, 0.0, hi)), st.floats(min_value=0.0, max_value=hi).map(repr))


# --wfs-field: anything but an accepted field above 0 (each a calibration of its own at a sensing
# oversampling of 3 to 6, minutes at the limit); 0, the sampled field, is cheap
FIELDS = NUMBERS.filter(lambda t: not _in(t, 0.0, 0.4))


def _in(text: str, lo: float, hi: float) -> bool:
    try:
        v = float(text)
    except ValueError:
        return False
    return lo < v <= 10 * hi or v != v  # NaN is refused anyway, but keep "nan" in the other branch


FAST_LOOP = ["--mag", "16.5", *CHEAP_PYRAMID, "--duration", "0.05"]
OGTL_LOOP = ["--mag", "16.5", *CHEAP_PYRAMID, "--duration", "0.8", "--ogtl", "--period", "0.25"]
OPTIMIZE = [
    "--mag",
    "16.5",
    *CHEAP_PYRAMID,
    "--no-ogtl",
    "--period",
    "1.1",
    "--duration",
    "1.1",
    "--measure",
    "0.1",
]
CHEAP_OPTICS = ["--binning", "4", *CHEAP_PYRAMID]

# (command, base arguments, option, strategy, time limit in s)
CASES = [
    ("configure", [], "--mag", NUMBERS, 10),
    *[
        ("filter analyze", ["--rate", "1700", "--gain", "0.3", "--control", c], o, s, 10)
        for c, o, s in [
            ("int", "--rate", LISTS),
            ("int", "--gain", LISTS),
            ("int", "--delay-frames", LISTS),
            ("int", "--delay-ms", LISTS),
            ("int", "--chi", LISTS),
            ("leaky", "--forgetting", LISTS),
            ("iir", "--zeros", LISTS),
            ("iir", "--poles", LISTS),
        ]
    ],
    *[
        ("filter design", ["--rate", "1700"], o, NUMBERS, 60)
        for o in ["--rate", "--epsilon", "--seeing", "--wind", "--L0", "--noise", "--resonance-line", "--delay-ms", "--seed"]
    ],
    *[("optics atmosphere", [], o, NUMBERS, 10) for o in ["--seeing", "--wind", "--L0"]],
    *[("optics calibrate", CHEAP_OPTICS, o, NUMBERS, 120) for o in ["--binning", "--modes", "--modulation", "--oversampling"]],
    ("optics calibrate", CHEAP_OPTICS, "--wfs-field", FIELDS, 120),
    *[
        ("optics gains", [*CHEAP_OPTICS, "--screens", "1"], o, s, 120)
        for o, s in [
            ("--seeing", NUMBERS),
            ("--L0", NUMBERS),
            ("--controlled-fraction", NUMBERS),
            ("--screens", small(4)),
            ("--seed", NUMBERS),
        ]
    ],
    *[
        ("loop run", FAST_LOOP, o, s, 120)
        for o, s in [
            ("--mag", NUMBERS),
            ("--seeing", NUMBERS),
            ("--wind", NUMBERS),
            ("--L0", NUMBERS),
            ("--duration", small(0.1)),
            ("--seed", NUMBERS),
            ("--oversampling", NUMBERS),
            ("--wfs-field", FIELDS),
            ("--gains", LISTS),
            ("--misregistration", LISTS),
            ("--ncpa", NUMBERS),
            ("--ncpa-offset-fraction", NUMBERS),
        ]
    ],
    *[("loop run", OGTL_LOOP, o, NUMBERS, 120) for o in ["--period", "--probe-mode", "--probe-amplitude", "--probe-frequency"]],
    *[
        ("optimize gains", OPTIMIZE, o, s, 180)
        for o, s in [
            ("--period", NUMBERS),
            ("--duration", small(1.2)),
            ("--measure", small(0.2)),
            ("--seeing", NUMBERS),
            ("--seed", NUMBERS),
        ]
    ],
    *[
        ("loop run", [*FAST_LOOP, "--telemetry", "{out}.h5"], o, s, 120)
        for o, s in [("--telemetry-every", NUMBERS), ("--telemetry-fields", LISTS)]
    ],
    ("telemetry psd", ["{record}"], "--modes", LISTS, 30),
    ("telemetry psd", ["{record}", "--pseudo-open-loop"], "--delay-frames", NUMBERS, 30),
    *[
        ("optimize gains", ["--method", "mgm", "--telemetry", "{record}"], o, s, 60)
        for o, s in [("--delay-frames", NUMBERS), ("--resonance", CHOICES)]
    ],
    ("telemetry identify", ["{record}"], "--delay-frames", NUMBERS, 60),
    ("telemetry identify", ["{record}"], "--resonance", CHOICES, 60),
    # the readers of other systems' records: an LBT folder in its supervisor's layout, an AOT quad-cell loop
    ("telemetry psd", ["{lbt}"], "--modes", LISTS, 30),
    ("telemetry identify", ["{lbt}"], "--delay-frames", NUMBERS, 60),
    ("telemetry psd", ["{aot}", "--pseudo-open-loop"], "--delay-frames", NUMBERS, 30),
    ("telemetry identify", ["{aot}"], "--delay-frames", NUMBERS, 60),
    ("optimize gains", ["--method", "mgm", "--telemetry", "{aot}"], "--delay-frames", NUMBERS, 60),
    *[("rtc check", ["{gains}", "--mag", "16.5"], o, NUMBERS, 30) for o in ["--modulus-margin", "--gain-margin", "--phase-margin"]],
    ("rtc check", ["{gains}"], "--mag", NUMBERS, 30),
    ("rtc check", ["{gains}", "--mag", "16.5"], "--misregistration", REGISTRATIONS, 120),
    ("sweep", ["{grid}", "--out", "{out}", "--yes"], "--workers", NUMBERS, 180),
]
GRID = "magnitude = 16.5\noversampling = 1\nwfs_field = 0\nduration = 0.05\n"


class Timeout(Exception):
    pass


WALL_FACTOR = 5  # the wall-clock backstop, in multiples of the CPU-time limit


@contextlib.contextmanager
def time_limit(seconds: float):
    """Raise Timeout once the process has used ``seconds`` of CPU time (ITIMER_PROF: what a
    runaway computation consumes, whatever else shares the machine; a contended 2-core runner
    stretched one design's wall time from 10 s to 49 s), or after ``WALL_FACTOR`` times that
    in wall time (a hang that waits without computing)."""

    def alarm(signum, frame):
        raise Timeout(f"no answer within {seconds} s of CPU time ({WALL_FACTOR * seconds} s of wall time)")

    previous = {s: signal.signal(s, alarm) for s in (signal.SIGPROF, signal.SIGALRM)}
    signal.setitimer(signal.ITIMER_PROF, seconds)
    signal.setitimer(signal.ITIMER_REAL, WALL_FACTOR * seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0)
        signal.setitimer(signal.ITIMER_REAL, 0)
        for s, handler in previous.items():
            signal.signal(s, handler)


def invoke(args: list[str], limit: float) -> tuple[int, str, str, float]:
    out, err = io.StringIO(), io.StringIO()
    t0 = time.perf_counter()
    with time_limit(limit), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main(args)
    return status, out.getvalue(), err.getvalue(), time.perf_counter() - t0


def no_constants(token):
    raise AssertionError(f"{token} in JSON output")


def check_contract(args: list[str], limit: float) -> None:
    status, out, err, seconds = invoke(args, limit)
    assert status in (0, 2, 3), (args, status, err)
    assert "Traceback" not in err
    if status == 2:
        assert err.count("\n") == 1 and err.startswith("soulctl: error: "), (args, err)
        assert out == "", (args, out)
    else:
        json.loads(out, parse_constant=no_constants)


@pytest.mark.slow
@pytest.mark.parametrize("command, base, option, values, limit", CASES, ids=[f"{c[0]} {c[2]}" for c in CASES])
def test_every_numeric_option_keeps_the_contract(command, base, option, values, limit, tmp_path_factory):
    cache = str(tmp_path_factory.getbasetemp() / "property-cache")
    uses_cache = command.split()[0] in ("loop", "optimize", "sweep") or command in (
        "optics calibrate",
        "optics gains",
        "telemetry identify",
        "rtc check",
    )

    grid = tmp_path_factory.mktemp("grid") / "grid.toml"
    grid.write_text(GRID)
    outs = iter(range(10**6))
    record = grid.parent / "record.h5"  # a short recorded loop, for the commands that read one
    if "{record}" in base:
        assert main(["loop", "run", *FAST_LOOP[:4], "--duration", "1", "--telemetry", str(record), "--cache-dir", cache, "--json"]) == 0
    gains = grid.parent / "gains.toml"  # R16.5's 90 modes
    gains.write_text("gains = [" + ", ".join(["0.3"] * 90) + "]\n")
    lbt, aot = grid.parent / "Data_20190302_190223", grid.parent / "quad.fits"
    if "{lbt}" in base:
        write_real_folder(grid.parent, frames=1500)
    if "{aot}" in base:
        write_aot(aot, *tip_tilt_loop(5000, 0.6), 0.6)

    @PROFILE
    @given(value=values)
    def check(value):
        fill = {
            "grid": str(grid),
            "out": str(grid.parent / f"out{next(outs)}"),
            "record": str(record),
            "gains": str(gains),
            "lbt": str(lbt),
            "aot": str(aot),
        }  # a new folder per sweep
        args = [
            *command.split(),
            *(a.format(**fill) for a in base),
            option,
            value,
            "--json",
            *(["--cache-dir", cache] if uses_cache else []),
        ]
        check_contract(args, limit)

    check()


SEEDED = [(c, b, lim) for c, b, o, _, lim in CASES if o == "--seed"]


@pytest.mark.slow
@pytest.mark.parametrize("command, base, limit", SEEDED, ids=[c for c, _, _ in SEEDED])
@pytest.mark.parametrize("seed", [0, 2**32, 2**63 - 1])
def test_every_seed_in_the_stated_range_runs(command, base, limit, seed, tmp_path_factory):
    """Every command with --seed runs at the ends of the stated range and past the legacy
    32-bit seeds (a search that seeded numpy's RandomState failed at 2^32).  The cheap
    optimisation case's loop does not close (R16.5 at --oversampling 1: 2.4 um of residual,
    Strehl 0.008), so MGM's gains may see it diverge in the paired evaluation: exit 3, its
    JSON written, is the contract's answer for that seed."""
    from soulctl.ranges import SEED

    assert SEED.contains(seed)
    cache = str(tmp_path_factory.getbasetemp() / "property-cache")
    uses_cache = command.split()[0] in ("loop", "optimize") or command == "optics gains"
    args = [*command.split(), *base, "--seed", str(seed), "--json", *(["--cache-dir", cache] if uses_cache else [])]
    status, out, err, _ = invoke(args, limit)
    assert status == 0 or (status == 3 and command == "optimize gains" and "diverged" in err), (args, err)
    json.loads(out, parse_constant=no_constants)
