"""The paths that build a closed loop (loop run, loop run --mgm --ogtl, optimize gains live and
offline, a sweep row), each on a small configuration: the command lines and the figures they
gave, recorded on the code before the run description replaced the four run builders, and
recorded again when MGM's significance test changed the gains MGM applies (its three cases
moved; the others by the last bits of the recording machine only, within LINEAR_RTOL).

    python tests/regression_runs.py          # rewrites tests/data/run_regression.json

``tests/loop/test_run_regression.py`` re-runs every case and asks for the same figures.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import sys
import tempfile
from pathlib import Path

from cheap import CHEAP_PYRAMID

RECORD = Path(__file__).parent / "data" / "run_regression.json"

SMALL = ["--mag", "16.5", *CHEAP_PYRAMID, "--seed", "3"]
CASES = {
    "loop run": ["loop", "run", *SMALL, "--duration", "0.8", "--seeing", "0.8", "--wind", "12", "--L0", "30"],
    "loop run, int, gains, no noise": [
        "loop",
        "run",
        *SMALL,
        "--duration",
        "0.2",
        "--tt-control",
        "int",
        "--gains",
        "0.3,0.4,0.2",
        "--no-noise",
        "--no-resonance",
    ],
    "loop run --mgm --ogtl": ["loop", "run", *SMALL, "--duration", "2", "--mgm", "--ogtl", "--period", "0.7"],
    "optimize gains": ["optimize", "gains", *SMALL, "--period", "1.1", "--duration", "1.1", "--measure", "0.1"],
    "optimize gains, offline": ["optimize", "gains", "--telemetry", "{telemetry}", "--method", "mgm"],
    # SOUL's 2.1" field, the default since after the run description (recorded then): the other
    # cases keep the sampled field they were recorded with (--wfs-field 0 in SMALL)
    "loop run, SOUL's field": ["loop", "run", "--mag", "16.5", "--oversampling", "1", "--seed", "3", "--duration", "0.3"],
}
# The auxiliary loops decide (OGTL holds or updates k, MGM steps): on another machine the last
# bits of the FFTs and BLAS differ, the linear paths then agree to ~1e-7 and these paths, whose
# decisions amplify that, do not; they are compared where the linear paths agree exactly.
ADAPTIVE = ("loop run --mgm --ogtl", "optimize gains")
LINEAR_RTOL = 1e-5  # the linear paths on any machine
SAME_PLATFORM_RTOL = 1e-12  # the linear paths on the recording's numerical platform
# Figures compared: dotted paths into each command's JSON.
FIGURES = {
    "loop run": ["metrics.strehl", "metrics.tt_jitter_mas", "metrics.residual_nm", "metrics.tt_jitter_pol_mas"],
    "loop run, int, gains, no noise": ["metrics.strehl", "metrics.tt_jitter_mas", "metrics.residual_nm"],
    "loop run --mgm --ogtl": ["metrics.strehl", "metrics.residual_nm", "final_sensitivity", "final_gains"],
    "optimize gains": ["before.strehl", "after.strehl", "gains"],
    "optimize gains, offline": ["gains"],
    "loop run, SOUL's field": ["metrics.strehl", "metrics.tt_jitter_mas", "metrics.residual_nm", "configuration.field_of_view_arcsec"],
}


def _run(args: list[str]) -> dict:
    from soulctl.cli.app import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = main([*args, "--json"])
    if status != 0:
        raise RuntimeError(f"{' '.join(args)}: exit {status}: {err.getvalue()}")
    return json.loads(out.getvalue())


def _get(d, path: str):
    for key in path.split("."):
        d = d[key]
    return d


def figures(cache_dir: str) -> dict:
    """Every case's figures, run now (the offline case reads the first run's telemetry)."""
    result = {}
    with tempfile.TemporaryDirectory() as tmp:
        telemetry = str(Path(tmp) / "t.h5")
        for name, args in CASES.items():
            args = [a.format(telemetry=telemetry) for a in args]
            if name == "loop run":
                args = [*args, "--telemetry", telemetry]
            out = _run([*args, "--cache-dir", cache_dir])
            result[name] = {path: _get(out, path) for path in FIGURES[name]}
    return result


def close(a, b, rtol: float = 1e-9) -> bool:
    if isinstance(a, list):
        return len(a) == len(b) and all(close(x, y, rtol) for x, y in zip(a, b))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(close(a[k], b[k], rtol) for k in a)
    if a is None or b is None:
        return a is b
    return math.isclose(a, b, rel_tol=rtol, abs_tol=1e-12)


if __name__ == "__main__":
    cache = sys.argv[1] if len(sys.argv) > 1 else tempfile.mkdtemp()
    RECORD.write_text(json.dumps({"cases": CASES, "figures": figures(cache)}, indent=1) + "\n")
    print(f"wrote {RECORD}")
