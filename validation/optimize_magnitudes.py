"""Gain optimisation over the look-up table's magnitudes (issue: MGM and OGTL that never drive
the loop unstable).  Not in CI: the 40x40 cases cost minutes each.

For every R magnitude x seeing x seed x variant, `optimize gains` with default options except
the short run lengths (``--duration`` 5 update periods, ``--measure`` 0.5 s): the configuration
of the look-up table, its default period, initial gains, probe and safety net.  Variants:
mgm+ogtl (the default), trial+ogtl, mgm, trial.  "before" and "after" are `optimize`'s
paired evaluation (the initial and the optimised gains on the run's own turbulence and noise)
over ``--windows`` consecutive windows of ``--window`` s (6 x 1 s: the difference one window
shows depends on what the turbulence does in it; R17.5, 0.6": -0.040 in one 0.5 s window,
-0.0025 +- 0.004 over six of 1 s), more below 750 Hz so that every rate has as many frames
(``windows_for``: 45 at 100 Hz); the run's own phases are recorded beside them
(``during_run``).  The checks use the windows' means (rows recorded before `optimize` had
windows carry the one 0.5 s window as "before"/"after" and the windows apart):

* no divergence and no safety net that gave up (exit 3);
* Strehl after >= Strehl before - 0.01;
* MGM's Strehl after >= trial-and-error's - 0.01 (same magnitude, seeing, seed and OGTL: the
  same screens, ``session_seconds``).

The pyramid has the runs' default field of view, SOUL's 2.1" (``defaults.WFS_FIELD_ARCSEC``;
the rows of the codes before it became the default, up to a442873e85c5, ran the sampled field
and make another table).

The variants of one magnitude, seeing and seed run one after the other in one worker, those
with the same OGTL setting sharing their *before* evaluation (``SharedEvaluations``).  Rows are
appended to a JSON-lines file as points finish (a stopped run keeps what it did and is resumed
by running again with the same --out, on the same code: rows of other code are run again);
the summary table is printed at the end.

Run:  python -m validation.optimize_magnitudes [--mags 16.5,17.5] [--seeings 0.6,1.0,1.5]
      [--seeds 1,2,3] [--variants mgm+ogtl,trial+ogtl,mgm,trial] [--windows 6] [--window 1.0]
      [--influence gaussian|thin-plate] [--workers 2] [--out FILE]
Table of several files' rows made with the current code (each row carries the fingerprint of
the code that made it, ``code_fingerprint``; ``--code any`` takes every row):
      python -m validation.optimize_magnitudes --table FILE [FILE ...] [--code HASH[,HASH...]|any]
      [--code-before-give-up HASH[,HASH...]] [--code-without-ogtl HASH[,HASH...]]
      [--code-without-restores HASH[,HASH...]] [--code-without-mgm HASH[,HASH...]]
      [--code-calibrated-k HASH[,HASH...]]
The first of these admits rows of code that differs from the current only in what follows the
safety net's giving up, when they have fewer restores than a give-up needs (those runs were
alike); the second the rows without OGTL of code that differs only where OGTL runs; the third
the rows without a safety restore of code that differs only in what a restore sets; the fourth
the trial-and-error rows of code that differs only in MGM; the fifth the rows of code before
the optimisers waited for OGTL's calibrated k that this wait cannot have changed.  A fingerprint given to several
differs in each way, and its rows must meet each condition.
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

import numpy as np
from rich.console import Console
from rich.table import Table

from soulctl import defaults
from soulctl.cli.common import default_cache_dir
from soulctl.control.gains import gain_groups
from soulctl.loop import optimize as optimize_module
from soulctl.loop.auxloops import SafetyNet, summary
from soulctl.loop.chi_model import plant_model
from soulctl.loop.optimize import _session, optimize
from soulctl.loop.run import calibration_for
from soulctl.loop.schedule import OptimizeRequest, default_period_s, session_seconds
from soulctl.observation import observation_for_magnitude
from soulctl.optics.asm import DEFAULT_INFLUENCE, INFLUENCES
from soulctl.optics.cache import ArrayCache
from soulctl.optics.ncpa import NcpaSpec
from soulctl.run_config import AtmosphereSpec, RunConfig
from validation.provenance import code_fingerprint, machine, provenance

MAGS = (8.0, 9.7, 10.9, 11.9, 13.0, 14.5, 15.5, 16.5, 17.5, 18.5)
SEEINGS = (0.6, 1.0, 1.5)
VARIANTS = ("mgm+ogtl", "trial+ogtl", "mgm", "trial")
DURATION_PERIODS, MEASURE_S = 5, 0.5  # short runs: MGM makes 5 updates; trial-and-error its default sequences
TOLERANCE = 0.01
# A give-up ends a streak of give_up + 1 checks in trouble, with a restore every IN_A_ROW checks
# at most: rows with fewer restores never came near one (tests/loop/test_auxloops.py)
FEWEST_RESTORES = SafetyNet(1).give_up // SafetyNet.IN_A_ROW
WINDOWS, WINDOW_S = 6, 1.0  # the checks' paired evaluation: six consecutive windows of 1 s at least ...
REFERENCE_RATE_HZ = 750.0  # ... and as many frames as six of 1 s at R14.5's 750 Hz (``windows_for``)
OUT = Path(__file__).parent / "results" / "optimize_magnitudes.jsonl"


def _run(obs, seeing: float, seed: int, influence: str = DEFAULT_INFLUENCE, wfs_field: float = defaults.WFS_FIELD_ARCSEC):
    """The run of a point: the look-up table's observation, defaults elsewhere (the mirror's
    influence functions and the pyramid's field of view as asked: the grid ran on the Gaussian
    mirror and the sampled field, the defaults then)."""
    return RunConfig(
        observation=obs,
        atmosphere=AtmosphereSpec(seeing_arcsec=seeing),
        seed=seed,
        ncpa=NcpaSpec(),
        influence=influence,
        wfs_field_arcsec=wfs_field,
    ).request()  # no NCPA, as the grid's first rows


def paired_windows(r) -> dict | None:
    """The windows of result ``r``'s paired evaluation (None if diverged)."""
    if r.before is None or r.after is None:
        return None
    _, error = r.strehl_difference()
    before, after = r.before.window_strehls, r.after.window_strehls
    return {
        "window_s": r.request.window,
        "before": before,
        "after": after,
        "mean_before": r.before.strehl,
        "mean_after": r.after.strehl,
        "standard_error": error,
    }


def point_arguments(
    doc: str, mag: float = 11.9, seeing: float = 1.5, seed: int = 3, wfs_field: float = defaults.WFS_FIELD_ARCSEC
) -> argparse.ArgumentParser:
    """The command line of a script about one grid point (--mag, --seeing, --seed, --variant,
    --wfs-field, --out), its defaults the point asked about; the script adds its own options.
    Results recorded before SOUL's 2.1" field was the runs' default are reproduced with
    --wfs-field 0."""
    p = argparse.ArgumentParser(description=doc.splitlines()[0])
    p.add_argument("--mag", type=float, default=mag)
    p.add_argument("--seeing", type=float, default=seeing)
    p.add_argument("--seed", type=int, default=seed)
    p.add_argument("--variant", default="mgm+ogtl")
    p.add_argument("--wfs-field", type=float, default=wfs_field, help="the pyramid's field of view, arcsec (0: the sampled field)")
    p.add_argument("--out", type=Path, default=None)
    return p


def windows_for(rate_hz: float, windows: int = WINDOWS) -> int:
    """Windows of the paired evaluation at ``rate_hz``: at least ``windows``, and as many
    frames as ``windows`` at REFERENCE_RATE_HZ, whatever their length (45 at 100 Hz).
    Why: at the faint end the two loops of the pairing do not stay paired - the noise is
    drawn from the intensities (one EMCCD draw per lit pixel), so the least difference of
    state shifts every later draw
    (R18.5, 0.6": the initial gains x (1 + 1e-4) move the six windows' mean by +0.002 and one
    window by up to 0.013; x 1.01 by -0.010) - and the verdict's noise is that of the frames
    (the same point: -0.011 on six windows, -0.003 +- 0.003 on 48)."""
    return max(windows, math.ceil(windows * REFERENCE_RATE_HZ / rate_hz - 1e-9))


def point_request(
    mag: float,
    seeing: float,
    seed: int,
    variant: str,
    windows: int = WINDOWS,
    window_s: float = WINDOW_S,
    influence: str = DEFAULT_INFLUENCE,
    modulation: float | None = None,
    wfs_field: float = defaults.WFS_FIELD_ARCSEC,
) -> OptimizeRequest:
    """The `optimize gains` request of a grid point: the look-up table's observation (its
    modulation replaced by ``modulation`` lambda/D if given, for diagnostics), MGM for
    DURATION_PERIODS update periods, ``windows_for`` its frame rate."""
    method, ogtl = variant.split("+")[0], variant.endswith("+ogtl")
    obs = observation_for_magnitude(mag)
    if modulation is not None:
        obs = replace(obs, modulation_lambda_over_d=modulation)
    duration = DURATION_PERIODS * default_period_s(obs)
    return OptimizeRequest(
        run=_run(obs, seeing, seed, influence, wfs_field),
        method=method,
        duration_s=duration,
        ogtl=ogtl,
        measure_s=MEASURE_S,
        windows=windows_for(obs.frame_rate_hz, windows),
        window_s=window_s,
    )


class PointLoops(NamedTuple):
    """What a script needs to re-close a grid point's loops (``loop_optical_gains.py``,
    ``lock_loss.py``): its request, cache, calibration, design gains, and the optimisation's
    session (the initial gains on ``session.loop``, a fresh OGTL task per ``session.new_ogtl()``)."""

    request: OptimizeRequest
    cache: ArrayCache
    cal: object
    design: object
    session: object


def point_loops(
    mag: float,
    seeing: float,
    seed: int,
    variant: str = "mgm+ogtl",
    modulation: float | None = None,
    wfs_field: float = defaults.WFS_FIELD_ARCSEC,
) -> PointLoops:
    """``PointLoops`` of a grid point (``point_request``), MGM's plant with OGTL's chi."""
    request = point_request(mag, seeing, seed, variant, modulation=modulation, wfs_field=wfs_field)
    r = request.run
    cache = ArrayCache(str(default_cache_dir()))
    cal = calibration_for(r, cache)
    design = r.design_gains()
    chi = plant_model(cal, cache, True, request.ogtl_settings.mode, request.chi_seeing)
    return PointLoops(request, cache, cal, design, _session(request, cal, cache, design, chi))


def run_case(
    mag: float,
    seeing: float,
    seed: int,
    variant: str,
    cache_dir: str,
    windows: int = WINDOWS,
    window_s: float = WINDOW_S,
    influence: str = DEFAULT_INFLUENCE,
    wfs_field: float = defaults.WFS_FIELD_ARCSEC,
) -> dict:
    """One `optimize gains` point; the row of the results."""
    t0 = time.perf_counter()
    request = point_request(mag, seeing, seed, variant, windows, window_s, influence, wfs_field=wfs_field)
    cache = ArrayCache(cache_dir)
    r = optimize(request, cache)
    records = {name: r.loop.telemetry.aux_arrays(name) for name in r.loop.telemetry.aux}
    return {
        "mag": mag,
        "seeing": seeing,
        "seed": seed,
        "variant": variant,
        "influence": influence,
        "wfs_field_arcsec": wfs_field,
        "period_s": request.period_s,
        "diverged_at": r.diverged_at,
        "diverged_in": r.diverged_in,
        "before": r.before.strehl if r.before else None,
        "after": r.after.strehl if r.after else None,
        "safety_restores": r.safety_events,
        "optimiser_held": r.held,
        "during_run": {k: v.strehl for k, v in r.during_run.items()},
        "sensitivities": list(r.sensitivities),
        "sensitivities_evaluated": [m.sensitivity if m else None for m in (r.before, r.after)],
        "settled_k": [m.settled.k if m and m.settled else None for m in (r.before, r.after)],
        "k": r.loop.rtc_parameters.sensitivity,
        "gain_groups": {name: [float(r.initial_gains[m].mean()), float(r.gains[m].mean())] for name, m in gain_groups(len(r.gains))},
        "aux": summary(records),
        "windows": paired_windows(r),
        "seconds": time.perf_counter() - t0,
        "machine": machine(),
    }


class SharedEvaluations:
    """The paired evaluation of a gain set, measured once for the variants of one point.

    MGM and trial-and-error on one magnitude, seeing, seed and OGTL setting share everything
    up to the optimisation (the screens are sized alike, ``session_seconds``), so their
    *before* evaluation - the initial gains at the k of the end of *before*, or with OGTL from
    k = 1 with a fresh task of the same settings and settling - is the same loop, frame for
    frame.  Measuring it once saves a fifth of a point's time.  Wraps
    ``soulctl.loop.optimize.evaluate`` for the duration of a ``with`` block; a key holds
    everything the evaluation depends on besides the run itself (the block runs one point),
    the gains to 12 decimals: trial-and-error's kept gains reuse the *before* evaluation
    (``shared_evaluations`` 2 from rows made after that change, 1 before; the RTC's float32
    gains make the two evaluations the same loop either way), and with OGTL so does *after*'s
    evaluation frozen at *before*'s settled k when the same gains settle there themselves."""

    def __init__(self):
        self.memo: dict = {}
        self.hits = 0

    def __enter__(self):
        self._evaluate = optimize_module.evaluate

        def shared(request, cal, design, gains, k, offsets=False, progress=None, ogtl=None, freeze=None):
            task = None if ogtl is None else (ogtl.period_frames, ogtl.settings, ogtl.k_max, ogtl.amplitude_nm)
            fixed = None if ogtl is not None else (float(k), bool(offsets))  # with OGTL the loop starts at k = 1
            # gains to 12 decimals: trial-and-error's kept gains (best x shape) differ from the
            # initial ones in the last bits, and are the same loop
            key = (session_seconds(request), request.windows, request.window, np.round(gains, 12).tobytes(), fixed, task)
            # a loop frozen at the k its own OGTL settles to is the loop measured unfrozen
            own = self.memo.get((key, None))
            hit = self.memo.get((key, freeze)) or (own if own is not None and own.settled == freeze else None)
            if hit is not None:
                self.hits += 1
                return copy.deepcopy(hit)
            metrics = self._evaluate(request, cal, design, gains, k, offsets, progress, ogtl, freeze)
            self.memo[(key, freeze)] = copy.deepcopy(metrics)
            return metrics

        optimize_module.evaluate = shared
        return self

    def __exit__(self, *exc):
        optimize_module.evaluate = self._evaluate


def run_point(
    mag: float,
    seeing: float,
    seed: int,
    variants: list[str],
    cache_dir: str,
    windows: int = WINDOWS,
    window_s: float = WINDOW_S,
    influence: str = DEFAULT_INFLUENCE,
) -> list[dict]:
    """The variants of one magnitude, seeing and seed, run one after the other in one process
    so that those with the same OGTL setting share their *before* evaluation."""
    rows = []
    for ogtl in (True, False):
        with SharedEvaluations() as shared:
            for v in (v for v in variants if v.endswith("+ogtl") == ogtl):
                row = run_case(mag, seeing, seed, v, cache_dir, windows, window_s, influence)
                row["shared_evaluations"] = shared.hits
                rows.append(row)
    return rows


def _key(row: dict) -> tuple:
    return (row["mag"], row["seeing"], row["seed"], row["variant"])


def judged(row: dict, which: str) -> float | None:
    """The Strehl ratio a check uses: the windows' mean where the row has them, else the one
    window (None: a diverged evaluation's)."""
    w = row.get("windows")
    return w[f"mean_{which}"] if w else row[which]


def checks(rows: list[dict]) -> list[dict]:
    """Per row: ok flags of the three checks (None where a comparison has no partner)."""
    by = {_key(r): r for r in rows}
    out = []
    for r in rows:
        ok_div = r["diverged_at"] is None and not r.get("aux", {}).get("safety", {}).get("gave_up", False)  # exit 3 either way
        ok_gain = ok_div and judged(r, "after") >= judged(r, "before") - TOLERANCE
        ok_mgm = None
        if r["variant"].startswith("mgm"):
            partner = by.get((r["mag"], r["seeing"], r["seed"], r["variant"].replace("mgm", "trial")))
            if partner is not None and partner["after"] is not None and r["after"] is not None:
                ok_mgm = judged(r, "after") >= judged(partner, "after") - TOLERANCE
        out.append({**r, "ok_divergence": ok_div, "ok_after_before": ok_gain, "ok_mgm_vs_trial": ok_mgm})
    return out


def render(rows: list[dict], console: Console) -> None:
    t = Table(title="optimize gains over the look-up table (H Strehl before -> after, the windows' mean, seeds in order; !: a miss)")
    for c in ("R", "variant", *[f'{s:g}"' for s in SEEINGS], "restores", "checks"):
        t.add_column(c, justify="right")
    cases = sorted({(r["mag"], r["variant"]) for r in rows}, key=lambda x: (x[0], VARIANTS.index(x[1])))
    for mag, variant in cases:
        cells = []
        sel = [r for r in rows if r["mag"] == mag and r["variant"] == variant]
        for s in SEEINGS:
            pts = sorted((r for r in sel if r["seeing"] == s), key=lambda r: r["seed"])
            cells.append(
                "  ".join(
                    "div"
                    if r["diverged_at"] is not None
                    else f"{judged(r, 'before'):.3f}->{judged(r, 'after'):.3f}" + ("" if passes(r) else "!")
                    for r in pts
                )
            )
        failed = len(misses(sel))
        t.add_row(f"{mag:g}", variant, *cells, str(sum(r["safety_restores"] for r in sel)), f"{len(sel) - failed}/{len(sel)}")
    console.print(t)


def read_rows(
    paths: list[Path],
    codes: set[str] | None,
    wanted: set | None = None,
    before_give_up: frozenset = frozenset(),
    without_ogtl: frozenset = frozenset(),
    without_restores: frozenset = frozenset(),
    without_mgm: frozenset = frozenset(),
    calibrated_k: frozenset = frozenset(),
) -> list[dict]:
    """The rows of ``paths`` (JSON lines) made with one of the code fingerprints ``codes``
    (None: any), or with older code whose differences from the current leave the row alike,
    one per case (a row of ``codes`` before any older code's, the first: a case run twice on
    one code gives the same row, and an older code's may be of another machine; of the older
    codes' the last in the files, the newest run), restricted to
    ``wanted`` cases if given.  Each further set names code that differs in one way, and admits
    the rows that way cannot reach: ``before_give_up`` what follows the safety net's giving up
    (rows with fewer restores than a give-up needs, ``FEWEST_RESTORES``), ``without_ogtl``
    where OGTL runs (variants without it), ``without_restores`` what a safety restore sets
    (rows without a restore), ``without_mgm`` MGM (trial-and-error's rows), ``calibrated_k``
    the optimiser's wait for OGTL's calibrated k (rows without OGTL, or whose OGTL had raised
    k above 1 by the end of *before*: k rises only on an estimate it acted on, so OGTL was
    calibrated when the optimiser began).  A code in several sets differs in each of their
    ways: its rows need every condition."""
    conditions = (
        (before_give_up, lambda r: r["safety_restores"] < FEWEST_RESTORES),
        (without_ogtl, lambda r: not r["variant"].endswith("+ogtl")),
        (without_restores, lambda r: r["safety_restores"] == 0),
        (without_mgm, lambda r: not r["variant"].startswith("mgm")),
        (calibrated_k, lambda r: not r["variant"].endswith("+ogtl") or r["sensitivities"][0] > 1.0),
    )
    unique: dict = {}
    current: set = set()  # the cases whose row is of ``codes``: an older code's row gives way to it
    for path in paths:
        for r in (json.loads(line) for line in path.read_text().splitlines() if line.strip()):
            code, key = r.get("code"), _key(r)
            if wanted is not None and key not in wanted:
                continue
            if codes is None or code in codes:
                if key not in current:
                    unique[key] = r
                    current.add(key)
                continue
            ways = [ok for named, ok in conditions if code in named]
            if ways and all(ok(r) for ok in ways) and key not in current:
                unique[key] = r  # the last admitted: the newest run of the case
    return list(unique.values())


def passes(row: dict) -> bool:
    """A checked row passes every check (no MGM-vs-trial partner counts as a pass)."""
    return bool(row["ok_divergence"] and row["ok_after_before"] and row["ok_mgm_vs_trial"] is not False)


def misses(rows: list[dict]) -> list[dict]:
    """The checked rows that fail a check."""
    return [r for r in rows if not passes(r)]


def report(rows: list[dict], console: Console) -> None:
    """The table, the counts and each miss with its paired difference."""
    rows = checks(rows)
    render(rows, console)
    bad = misses(rows)
    restores = sum(r["safety_restores"] for r in rows)
    diverged = sum(r["diverged_at"] is not None for r in rows)
    console.print(f"{len(rows)} rows: {len(rows) - len(bad)} pass, {diverged} diverged, {restores} safety restores")
    for r in bad:
        b, a = judged(r, "before"), judged(r, "after")
        error = (r.get("windows") or {}).get("standard_error", float("nan"))
        case = _case(r)
        if r["diverged_at"] is not None or a is None or b is None:
            console.print(f"  miss: {case}: diverged in the {r.get('diverged_in') or 'run'} at frame {r['diverged_at']}")
            continue
        console.print(f"  miss: {case}: {b:.4f} -> {a:.4f} ({a - b:+.4f} +- {error:.4f})")


def not_run(wanted: set, rows: list[dict]) -> str:
    """The points (magnitude, seeing, seed) of ``wanted`` with a variant missing from ``rows``."""
    missing = sorted({c[:3] for c in wanted - {_key(r) for r in rows}})
    points = ", ".join(f'R{m:g} {s:g}" s{seed}' for m, s, seed in missing)
    return f"not run on this code: {len(missing)} points" + (f": {points}" if missing else "")


def _case(row: dict) -> str:
    return f'R{row["mag"]:g} {row["seeing"]:g}" seed {row["seed"]} {row["variant"]}'


def _judged_text(row: dict) -> str:
    """The windows' before -> after of a row; "-" for a side that has none (a diverged evaluation)."""
    b, a = judged(row, "before"), judged(row, "after")
    return " -> ".join("-" if x is None else f"{x:.4f}" for x in (b, a))


def _cases(a) -> list[tuple]:
    return [
        (float(m), float(s), int(seed), v)
        for m in a.mags.split(",")
        for s in a.seeings.split(",")
        for seed in a.seeds.split(",")
        for v in a.variants.split(",")
    ]


def run_grid(todo: list[tuple], out: Path, workers: int, windows: int, window_s: float, influence: str = DEFAULT_INFLUENCE) -> None:
    """Run the cases of ``todo`` that ``out`` has no row of this code for, appending their rows
    as points finish."""
    out.parent.mkdir(parents=True, exist_ok=True)
    # The code the workers run is the one imported at launch: a package re-installed during a
    # long grid must not relabel the rows that finish after it.
    launched = code_fingerprint()
    have = {_key(r) for r in read_rows([out], {launched})} if out.exists() else set()
    points: dict[tuple, list[str]] = {}  # (mag, seeing, seed) -> its variants to run
    for c in todo:
        if c not in have:
            points.setdefault(c[:3], []).append(c[3])
    order = sorted(points, key=lambda p: -p[0])  # the faint (fast) points first
    cache = str(default_cache_dir())
    with ProcessPoolExecutor(workers) as pool, out.open("a") as f:
        futures = [pool.submit(run_point, *p, points[p], cache, windows, window_s, influence) for p in order]
        for fut in as_completed(futures):
            for row in fut.result():
                row |= provenance(launched)
                f.write(json.dumps(row) + "\n")
                f.flush()
                outcome = f"{row['before']} -> {row['after']} (windows: {_judged_text(row)}; diverged at {row['diverged_at']})"
                print(f"{_case(row)}: {outcome}, {row['seconds']:.0f} s", flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--mags", default=",".join(f"{m:g}" for m in MAGS))
    p.add_argument("--seeings", default=",".join(f"{s:g}" for s in SEEINGS))
    p.add_argument("--seeds", default="1,2,3")
    p.add_argument("--variants", default=",".join(VARIANTS))
    p.add_argument("--windows", type=int, default=WINDOWS)
    p.add_argument("--window", type=float, default=WINDOW_S)
    p.add_argument(
        "--influence",
        default=DEFAULT_INFLUENCE,
        choices=INFLUENCES,
        help="the mirror's influence functions (every row of the results file: the default, thin-plate)",
    )
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--table", type=Path, nargs="+", help="run nothing: the table of these files' rows made with this code")
    p.add_argument("--code", default=None, help="with --table: the rows of these code fingerprints, comma-separated ('any': all rows)")
    p.add_argument(
        "--code-before-give-up",
        default="",
        help="with --table: also the rows of these fingerprints with fewer safety restores than a give-up needs (comma-separated)",
    )
    p.add_argument(
        "--code-without-ogtl",
        default="",
        help="with --table: also the rows without OGTL of these fingerprints (comma-separated)",
    )
    p.add_argument(
        "--code-without-restores",
        default="",
        help="with --table: also the rows without a safety restore of these fingerprints (comma-separated)",
    )
    p.add_argument(
        "--code-calibrated-k",
        default="",
        help="with --table: also the rows of these fingerprints without OGTL or whose k had left 1 by the end of before (comma-separated)",
    )
    p.add_argument(
        "--code-without-mgm",
        default="",
        help="with --table: also the trial-and-error rows of these fingerprints (comma-separated)",
    )
    a = p.parse_args()
    wanted = set(_cases(a))
    if a.table:
        codes = None if a.code == "any" else set((a.code or code_fingerprint()).split(","))
        named = (a.code_before_give_up, a.code_without_ogtl, a.code_without_restores, a.code_without_mgm, a.code_calibrated_k)
        extra = [frozenset(filter(None, x.split(","))) for x in named]
        rows = read_rows(a.table, codes, wanted, *extra)
        report(rows, Console(width=200))
        print(not_run(wanted, rows))
        return
    run_grid(sorted(wanted), a.out, a.workers, a.windows, a.window, a.influence)
    report(read_rows([a.out], {code_fingerprint()}, wanted), Console(width=200))


if __name__ == "__main__":
    main()
