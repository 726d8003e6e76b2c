"""One case of a sweep: its parameters -> a `loop run` (or a gain optimisation) -> one row.

The row holds every parameter, the metrics (Strehl at the band, Tip/Tilt jitter, residual),
the status (ok, diverged, failed), its reason, the run time, the seed and soulctl's version.
The same parameters and seed give the same numbers as `soulctl loop run` with the same
options (the sweep's check)."""

from __future__ import annotations

import time
import traceback

from .. import __version__, defaults, tables
from ..errors import InputError
from ..loop.optimize import optimize
from ..loop.run import RunRequest, run
from ..loop.run import calibration_setup as run_calibration_setup
from ..loop.schedule import OPTIMISER_OGTL, OptimizeRequest, default_period_s
from ..observation import BINNINGS, Observation
from ..optics.cache import ArrayCache
from ..optics.calibration import Calibration, CalibrationSetup, calibrate
from ..run_config import RunConfig
from .grid import FIELDS, case_id

DEFAULTS = {
    "seeing": defaults.SEEING_ARCSEC,
    "wind": defaults.WIND_M_S,
    "L0": defaults.L0_M,
    "duration": defaults.DURATION_S,
    "gain_method": "default",
    "band": defaults.BAND,
    "seed": defaults.SEED,
    "noise": True,
    "vibrations": True,
    "resonance": True,
    "oversampling": defaults.OVERSAMPLING,
    "wfs_field": defaults.WFS_FIELD_ARCSEC,
}
METRICS = ("strehl", "tt_jitter_mas", "residual_nm")
DESCRIPTION_KEY = "_run_description"  # the row's resolved run description (TOML), written beside the results
STATUS = ("ok", "diverged", "failed")


def case_description(case: dict) -> RunConfig:
    """The run description of a case: its parameters as overrides of the defaults' (the
    look-up table's configuration for the magnitude; a binning takes that binning's modes from
    the table, a frame rate the Tip/Tilt IIR of the nearest tabulated rate, an integrator below
    the table)."""
    if "binning" in case and not any(r.binning == case["binning"] for r in tables.magnitude_table()):
        raise InputError(f"binning {case['binning']} is not in the look-up table (accepted {', '.join(map(str, BINNINGS))})")
    return RunConfig().with_values({FIELDS.get(k, k): v for k, v in case.items() if k != "gain_method"})


def observation_for(case: dict) -> Observation:
    """The observation of a case (``case_description``)."""
    return case_description(case).observation


def run_request(case: dict) -> RunRequest:
    """The `loop run` request of a case (its parameters over `loop run`'s defaults)."""
    return case_description(case).request()


def calibration_setup(case: dict) -> CalibrationSetup:
    """What the case's calibration depends on (cases sharing it share one calibration)."""
    return run_calibration_setup(run_request(case))


def calibrate_case(setup: CalibrationSetup, cache_dir: str | None) -> Calibration:
    """The calibration of a set-up (from the disk cache when there)."""
    return calibrate(setup, ArrayCache(cache_dir))


def failed_row(case: dict, reason: str) -> dict:
    """The row of a case that did not run (``run_case`` fills it in when it does)."""
    return {
        "case_id": case_id(case),
        **DEFAULTS,
        **case,
        **dict.fromkeys(METRICS, float("nan")),
        "status": "failed",
        "reason": reason,
        "run_seconds": 0.0,
        "soulctl_version": __version__,
    }


def optimisation_period_s(duration_s: float, observation: Observation) -> float:
    """The update period of a case's gain optimisation: the default for its frame rate
    (``loop.optimize.default_period_s``, the rule of `optimize gains` and `loop run --mgm`),
    or half the duration (two updates) when that is shorter."""
    return min(default_period_s(observation), duration_s / 2)


def _finished(**metrics) -> dict:
    """The status and metrics of a case that ran: 'ok' with every metric, else 'failed' (a run
    too short for a metric has none, and an ok row always has all of them)."""
    missing = [k for k, v in metrics.items() if v is None]
    if missing:
        return {"status": "failed", "reason": f"the run is too short for {', '.join(missing)} (lengthen duration)"}
    return {"status": "ok", **metrics}


def _outcome(failure: str | None, figures) -> dict:
    """A run's status and metrics: 'diverged' with the reason when it failed, keeping the figures
    of a loop that ran to the end (lost to mis-registration, or beyond its safety net's help);
    else ``_finished``.
    ``figures``: ``LoopMetrics`` or ``PhaseMetrics`` (None when the loop diverged)."""
    values = None if figures is None else {k: getattr(figures, k) for k in ("strehl", "tt_jitter_mas", "residual_nm")}
    if failure is not None:
        return {"status": "diverged", "reason": failure} | {k: v for k, v in (values or {}).items() if v is not None}
    assert values is not None  # a loop that did not diverge has its metrics
    return _finished(**values)


def run_case(case: dict, calibration: Calibration | None = None, cache_dir: str | None = None) -> dict:
    """Run one case; never raises for a case's own failure (status 'failed' and the reason)."""
    p = {**DEFAULTS, **case}
    row = failed_row(case, "")
    t0 = time.perf_counter()
    try:
        description = case_description(case).resolved()
        row[DESCRIPTION_KEY] = description.to_toml()
        request = description.request()
        cache = ArrayCache(cache_dir)
        if p["gain_method"] == "default":
            result = run(request, cache, calibration=calibration, aux=description.auxiliary.live())  # as `loop run --config` runs it
            failure = result.failure()  # diverged, lost to mis-registration, or the safety net gave up
            row.update(_outcome(failure, result.metrics))
        else:
            period = optimisation_period_s(p["duration"], request.observation)
            run_request = description.request(ogtl=OPTIMISER_OGTL)  # automatic NCPA offsets come with the optimiser's OGTL
            optimised = optimize(
                # measured over the case's duration, one window, as a `loop run` case
                OptimizeRequest(
                    run=run_request, method=p["gain_method"], duration_s=p["duration"], period_s=period, measure_s=p["duration"], windows=1
                ),
                cache,
                calibration=calibration,
            )
            failure = optimised.failure()
            row.update(_outcome(None if failure is None else f"{failure} ({p['gain_method']})", optimised.after))
            if row["status"] == "ok" and optimised.held is not None:
                row["reason"] = f"{optimised.held} ({p['gain_method']})"  # ok, at the initial gains
    except InputError as e:
        row["reason"] = str(e)
    except Exception as e:  # recorded, never stops the sweep
        row["reason"] = f"{type(e).__name__}: {e} ({traceback.extract_tb(e.__traceback__)[-1].name})"
    row["run_seconds"] = time.perf_counter() - t0
    return row
