"""Benchmark of the command line's start-up: how long a user waits for soulctl to answer.

Cases, each the console script started as a new process (wall time from spawn to exit, with
the operating system's file cache warm: a first untimed run of each case):
  --version                      soulctl --version
  --help                         soulctl --help
  configure --mag 13 --json      the observation of an R = 13 star
  loop run --help                the longest help page

Each case runs --repeats times (default 20), interleaved with the other cases and, with
--baseline DIR, with the same cases run from another checkout (e.g. a `git worktree` of an
earlier commit: its Python sources on PYTHONPATH, the installed compiled core copied beside
them), so that both are measured side by side on the same machine state.

Targets (issue 84): --version and --help <= 0.3 s, configure --mag 13 <= 0.6 s (medians).

Run:  python -m bench.bench_startup [--repeats 20] [--baseline DIR] [--out bench/results/startup.json]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table

from bench.results_file import save

CASES = {
    "--version": ["--version"],
    "--help": ["--help"],
    "configure --mag 13 --json": ["configure", "--mag", "13", "--json"],
    "loop run --help": ["loop", "run", "--help"],
}
TARGETS_S = {"--version": 0.3, "--help": 0.3, "configure --mag 13 --json": 0.6}
ENTRY = "import sys; from soulctl.cli.app import main; sys.argv[0] = 'soulctl'; main()"
# A checkout's sources, not the installed package's: an editable install's import hook would
# otherwise answer for ``soulctl`` whatever PYTHONPATH says.
CHECKOUT_ENTRY = "import sys; sys.meta_path[:] = [f for f in sys.meta_path if 'editable' not in type(f).__module__]; " + ENTRY


def _installed_core() -> Path:
    """The compiled core of the installed package (found from outside any source tree)."""
    found = subprocess.run(
        [sys.executable, "-c", "import soulctl._core as c; print(c.__file__)"], cwd="/", capture_output=True, text=True, check=True
    )
    return Path(found.stdout.strip())


def _command(source: Path | None) -> tuple[list[str], dict[str, str], str]:
    """How to start soulctl: the installed console script, or a checkout's sources."""
    env = dict(os.environ, COLUMNS="80", TERM="dumb")
    if source is None:
        script = Path(sys.executable).parent / "soulctl"
        return [str(script)] if script.exists() else [sys.executable, "-c", ENTRY], env, "/"
    core = _installed_core()
    if not (source / "soulctl" / core.name).exists():
        shutil.copy2(core, source / "soulctl" / core.name)
    return [sys.executable, "-c", CHECKOUT_ENTRY], dict(env, PYTHONPATH=str(source)), str(source)


def _time(cmd: list[str], env: dict[str, str], cwd: str) -> float:
    t0 = time.perf_counter()
    done = subprocess.run(cmd, env=env, cwd=cwd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    dt = time.perf_counter() - t0
    if done.returncode != 0:
        sys.exit(f"{' '.join(cmd)} exited {done.returncode}: {done.stderr.decode()[-500:]}")
    return dt


def measure(sources: dict[str, Path | None], repeats: int) -> dict[str, dict[str, list[float]]]:
    runs = {label: _command(src) for label, src in sources.items()}
    times: dict[str, dict[str, list[float]]] = {label: {case: [] for case in CASES} for label in sources}
    for i in range(repeats + 1):  # the first round warms the file cache, untimed
        for case, args in CASES.items():
            for label, (cmd, env, cwd) in runs.items():
                dt = _time(cmd + args, env, cwd)
                if i:
                    times[label][case].append(dt)
    return times


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--repeats", type=int, default=20)
    p.add_argument("--baseline", type=Path, help="a checkout of the commit to compare with")
    p.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "startup.json")
    a = p.parse_args()
    sources: dict[str, Path | None] = {"this": None}
    if a.baseline is not None:
        sources = {"baseline": a.baseline.resolve(), "this": None}
    times = measure(sources, a.repeats)
    console = Console()
    table = Table(title=f"soulctl start-up, wall time of a new process (median / p90 of {a.repeats}, s)")
    table.add_column("case")
    for label in sources:
        table.add_column(label, justify="right")
    if "baseline" in sources:
        table.add_column("ratio", justify="right")
    table.add_column("target", justify="right")
    summary: dict[str, dict] = {}
    for case in CASES:
        row = [case]
        for label in sources:
            t = times[label][case]
            med, p90 = statistics.median(t), sorted(t)[int(0.9 * (len(t) - 1))]
            summary.setdefault(case, {})[label] = {"median_s": med, "p90_s": p90, "times_s": t}
            row.append(f"{med:.3f} / {p90:.3f}")
        if "baseline" in sources:
            row.append(f"{summary[case]['this']['median_s'] / summary[case]['baseline']['median_s']:.2f}")
        target = TARGETS_S.get(case)
        row.append("" if target is None else f"<= {target:g}")
        table.add_row(*row)
    console.print(table)
    baseline = None if a.baseline is None else str(a.baseline)
    save(a.out, {"benchmark": "startup", "repeats": a.repeats, "baseline": baseline, "cases": summary, "targets_s": TARGETS_S}, console)


if __name__ == "__main__":
    main()
