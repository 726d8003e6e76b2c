"""The paper's faint-star gain optimisation, its MGM transient and OGTL in a noise-dominated
loop (issue: MGM and OGTL that never drive the loop unstable).  Not in CI (~15 min).

* R13, 20x20, 980 Hz, FeII, 1.0", wind 5 m/s (paper: simulations 0.58, on sky 0.61-0.67):
  MGM with OGTL, default options, 3 seeds;
* R16.5, 10x10 (binning 4, 54 modes), 390 Hz, Ks, 1.0", 2 photons per sub-aperture per frame
  (paper: simulations 0.18, on sky 0.19-0.23): the same;
* the transient: the R13 case from 0.1x the initial gains, MGM every 5 s for 60 s: the time
  its gains take to settle (paper: about a minute), with the time series plotted;
* OGTL alone at R17.5 for 60 s: k within [1, k_max], the loop closed.

Run:  python -m validation.faint_cases [--seeds 1,2,3] [--transient-s 60] [--ogtl-s 60] [--out FILE]
      [--only R13,R16.5,ogtl,transient] [--vibrations lbt|lbt-onsky|FILE] [--wfs-field ARCSEC]
``--vibrations`` replaces the default Tip/Tilt vibrations of the two paper cases (e.g. the
on-sky level, ``lbt-onsky``: whether MGM, as on sky, brings those loops to the paper's range).
``--wfs-field`` gives every part's pyramid that field of view (``[run] wfs_field_arcsec``;
SOUL's 2.1, the default since it became the run's; 0: the sampled field, which
``faint_cases.json`` holds, from before) and writes ``faint_cases_wfs_field_<ARCSEC>.json``, the
transient's figures in ``transient_r13_wfs_field_<ARCSEC>/`` (the sampled field's: ``transient_r13/``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from soulctl import defaults, tables
from soulctl.cli.common import default_cache_dir
from soulctl.disturbance.vibrations import VibrationSpectrum
from soulctl.files import atomic_write_text
from soulctl.loop.auxloops import summary as aux_summary
from soulctl.loop.optimisers import LiveOptimisers
from soulctl.loop.optimize import optimize
from soulctl.loop.run import run
from soulctl.loop.schedule import OptimizeRequest
from soulctl.observation import observation_for_magnitude
from soulctl.optics.cache import ArrayCache
from soulctl.optics.ncpa import NcpaSpec
from soulctl.plots.gains import write_gain_figures
from soulctl.run_config import AtmosphereSpec, ControllerSpec, RunConfig
from validation.gain_optimisation import observation, settling_time  # noqa: E402
from validation.provenance import code_fingerprint, provenance

RESULTS = Path(__file__).parent / "results"
AT_1_ARCSEC = AtmosphereSpec(seeing_arcsec=1.0)  # the paper's faint cases
# The R13 night's wind, 4-6 m/s (the on-sky table of the project's field notes; the paper's
# text gives only the seeing); the default 8 m/s costs that loop 0.05 of FeII Strehl at fixed
# gains.  The R16.5 night's wind is not given: the default.
R13_NIGHT = AtmosphereSpec(seeing_arcsec=1.0, wind_m_s=5.0)
NO_NCPA = NcpaSpec()  # the paper's simulations carry no NCPA: the figures compare with them
PAPER = {"R13": (0.58, "0.61-0.67"), "R16.5": (0.18, "0.19-0.23")}


def r165_observation():
    """The paper's R16.5 loop: 10x10 sub-apertures (binning 4, that row's modes), 390 Hz, Tip/Tilt
    integrator (the roots table starts at 750 Hz)."""
    obs = observation_for_magnitude(16.5)
    b4 = next(row for row in tables.magnitude_table() if row.binning == 4)
    return dataclasses.replace(
        obs, binning=4, modes=b4.modes, frame_rate_hz=390.0, tt_control="int", tt_zeros=(), tt_poles=(), tt_filter_rate_hz=None
    )


def paper_case(
    label: str,
    obs,
    atmosphere: AtmosphereSpec,
    band: str,
    seeds,
    cache,
    vibrations: str | None = None,
    wfs_field: float = defaults.WFS_FIELD_ARCSEC,
) -> dict:
    rows = []
    lines = {} if vibrations is None else {"vibrations": VibrationSpectrum.read(vibrations)}
    for seed in seeds:
        config = RunConfig(observation=obs, atmosphere=atmosphere, band=band, seed=seed, ncpa=NO_NCPA, wfs_field_arcsec=wfs_field, **lines)
        r = optimize(OptimizeRequest(run=config.request(), method="mgm", measure_s=1.0), cache)
        records = {name: r.loop.telemetry.aux_arrays(name) for name in r.loop.telemetry.aux}
        rows.append(
            {
                "seed": seed,
                "diverged_at": r.diverged_at,
                "before": r.before.strehl if r.before else None,
                "after": r.after.strehl if r.after else None,
                "k": r.loop.rtc_parameters.sensitivity,
                "sensitivities": list(r.sensitivities),
                "safety_restores": r.safety_events,
                "aux": aux_summary(records),
            }
        )
        print(label, {k: v for k, v in rows[-1].items() if k != "aux"}, flush=True)
    after = [x["after"] for x in rows if x["after"] is not None]
    sim, sky = PAPER[label]
    mean, scatter = float(np.mean(after)), float(np.std(after)) if len(after) > 1 else 0.0
    return {
        "case": label,
        "band": band,
        "wind_m_s": atmosphere.wind_m_s,
        "vibrations": vibrations or "default",
        "wfs_field_arcsec": wfs_field,
        "runs": rows,
        "after_mean": mean,
        "after_scatter": scatter,
        "paper_simulation": sim,
        "paper_on_sky": sky,
        "ok": bool(len(after) == len(rows) and mean >= sim - scatter),
    }


def transient(obs, seconds: float, cache, wfs_field: float = defaults.WFS_FIELD_ARCSEC) -> dict:
    start = RunConfig(observation=obs).resolved().controller.gains
    low = RunConfig(
        observation=obs,
        atmosphere=R13_NIGHT,
        band="FeII",
        ncpa=NO_NCPA,
        controller=ControllerSpec(gains=tuple(0.1 * g for g in start)),
        wfs_field_arcsec=wfs_field,
    ).request()
    r = optimize(OptimizeRequest(run=low, method="mgm", duration_s=seconds, period_s=5.0, measure_s=1.0), cache)
    figures = RESULTS / ("transient_r13" if wfs_field == 0 else f"transient_r13_wfs_field_{wfs_field:g}")  # the first: the sampled field's
    figures.mkdir(parents=True, exist_ok=True)
    write_gain_figures(figures, {"mgm": r})
    settled = settling_time(r)
    return {
        "case": "R13 transient from 0.1x gains, MGM every 5 s",
        "wfs_field_arcsec": wfs_field,
        "diverged_at": r.diverged_at,
        "before": r.before.strehl if r.before else None,
        "after": r.after.strehl if r.after else None,
        "settling_s": settled,
        "ok": bool(r.diverged_at is None and settled <= 60.0),
        "figures": str(figures.relative_to(RESULTS.parents[1])),
    }


def ogtl_alone(seconds: float, cache, wfs_field: float = defaults.WFS_FIELD_ARCSEC) -> dict:
    obs = observation_for_magnitude(17.5)
    result = run(
        RunConfig(observation=obs, atmosphere=AT_1_ARCSEC, duration_s=seconds, ncpa=NO_NCPA, wfs_field_arcsec=wfs_field).request(),
        cache,
        aux=LiveOptimisers(mgm=False, ogtl=True),
    )
    og = result.telemetry.aux_arrays("ogtl")
    k = og.get("sensitivity", np.array([1.0]))
    s = aux_summary({name: result.telemetry.aux_arrays(name) for name in result.telemetry.aux})
    k_max = s["ogtl"]["k_max"]
    return {
        "case": f"OGTL alone, R17.5, {seconds:g} s",
        "wfs_field_arcsec": wfs_field,
        "diverged_at": result.diverged_at,
        "k_min": float(k.min()),
        "k_max_seen": float(k.max()),
        "k_bound": k_max,
        "statuses": s["ogtl"]["statuses"],
        "strehl": result.metrics.strehl if result.metrics else None,
        "ok": bool(result.diverged_at is None and 1.0 <= k.min() and k.max() <= k_max),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", default="1,2,3")
    p.add_argument("--transient-s", type=float, default=60.0)
    p.add_argument("--ogtl-s", type=float, default=60.0)
    p.add_argument("--out", type=Path, default=RESULTS / "faint_cases.json")
    p.add_argument("--only", default=None, help="comma list of R13, R16.5, ogtl, transient (default: all)")
    p.add_argument("--vibrations", default=None, help="the paper cases' vibrations: lbt, lbt-onsky or a file (default: the default)")
    p.add_argument(
        "--wfs-field",
        type=float,
        default=defaults.WFS_FIELD_ARCSEC,
        help="the paper cases' WFS field of view, arcsec (0: the sampled field)",
    )
    a = p.parse_args()
    if a.vibrations is not None and a.out == RESULTS / "faint_cases.json":  # not over the default level's results
        a.out = RESULTS / f"faint_cases_vibrations_{Path(a.vibrations).stem}.json"
    if a.out == RESULTS / "faint_cases.json":  # that file holds the sampled field's results
        a.out = RESULTS / f"faint_cases_wfs_field_{a.wfs_field:g}.json"
    cache = ArrayCache(default_cache_dir())
    seeds = [int(s) for s in a.seeds.split(",")]
    t0 = time.perf_counter()
    parts = {
        "R13": lambda: paper_case("R13", observation(13.0, 980.0), R13_NIGHT, "FeII", seeds, cache, a.vibrations, a.wfs_field),
        "R16.5": lambda: paper_case("R16.5", r165_observation(), AT_1_ARCSEC, "Ks", seeds, cache, a.vibrations, a.wfs_field),
        "ogtl": lambda: ogtl_alone(a.ogtl_s, cache, a.wfs_field),
        "transient": lambda: transient(observation(13.0, 980.0), a.transient_s, cache, a.wfs_field),
    }
    only = list(parts) if a.only is None else a.only.split(",")
    if set(only) - set(parts):
        p.error(f"--only takes {', '.join(parts)}")
    # the parts not run now are kept from the file (a re-run of one part keeps the others)
    out = json.loads(a.out.read_text()) if a.out.exists() and a.only is not None else {}
    code = code_fingerprint()  # each part says which code made it (parts may come from different runs)
    out.update({name: {**parts[name](), **provenance(code)} for name in only})
    out["wall_s"] = time.perf_counter() - t0
    a.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(a.out, json.dumps(out, indent=1, default=float))
    t = Table(title="Faint stars: MGM with OGTL at the paper's operating points, the transient, OGTL alone")
    for c in ("case", "result", "paper", "check"):
        t.add_column(c)
    for key in [k for k in ("R13", "R16.5") if k in out]:
        c = out[key]
        t.add_row(
            f"{key} ({c['band']})",
            f"SR {c['after_mean']:.3f} ± {c['after_scatter']:.3f} ({len(c['runs'])} seeds)",
            f"sim {c['paper_simulation']}, sky {c['paper_on_sky']}",
            "ok" if c["ok"] else "MISSED",
        )
    tr, og = out.get("transient"), out.get("ogtl")
    if tr is not None:
        result = f"settled in {tr['settling_s']:.0f} s, SR {tr['before']} -> {tr['after']}"
        t.add_row(tr["case"], result, "about a minute", "ok" if tr["ok"] else "MISSED")
    if og is not None:
        result = f"k {og['k_min']:.2f}..{og['k_max_seen']:.2f} (bound {og['k_bound']:.1f}), {og['statuses']}"
        t.add_row(og["case"], result, "-", "ok" if og["ok"] else "MISSED")
    Console(width=200).print(t)


if __name__ == "__main__":
    main()
