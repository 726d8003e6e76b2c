"""The estimated cost of a sweep, printed before it starts (and asked about above
``CONFIRM_ABOVE_S``).

A case costs ``CASE_FIXED_S`` (set-up, metrics) plus its frames times ``FRAME_MS`` of its
binning, oversampling and the pyramid's sensing oversampling (the oversampling, or the finer
one its field of view needs: 3 for SOUL's 2.1"); each distinct calibration costs
``CALIBRATION_S`` once (less when the cache holds it).  A sensing oversampling not measured
(fields above 2.26") is costed as a loop at that oversampling, scaled by the FFT's area above 4.
Frames: ``duration`` x the frame rate for a plain run; for
``gain_method = mgm`` the closing, OGTL's settling (at least 4 update periods, up to 12 until k
settles: the estimate counts 4) and three times
``duration`` (before, optimisation, after) and the paired evaluation (two loops, each closed,
settled for the longer of 1 s and 12 OGTL updates, ``schedule.evaluation_settle_s``, and
measured for ``duration``); for ``trial`` the closing, the settling, twice
``duration`` and the scan (8 gains and the initial one per group, 0.25 s or 100 frames each); the auxiliary loops' own cost
(MGM, OGTL) is not counted.

FRAME_MS, CASE_FIXED_S and CALIBRATION_S are CPU times measured by
``bench/bench_frame_cost.py`` (bench/results/frame_cost.json: one thread of the 2-core
development machine, default conditions; the field of view's ratio from
frame_cost_wfs_field.json); a faster machine takes less, a busy one more.
The wall time divides the CPU time by the workers and by ``PARALLEL_EFFICIENCY`` for more than
one (the local cluster measured 1.64x on 2 workers: bench/results/sweep.json).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

from ..control.gains import gain_groups
from ..errors import InputError
from ..loop.run import closing_frames
from ..loop.schedule import OGTL_SETTLING_PERIODS, OPTIMISER_OGTL, TRIAL_VALUES, default_sequence_s, evaluation_settle_s
from ..optics.pwfs import PyramidConfig
from .case import DEFAULTS, observation_for, optimisation_period_s

SOURCE = "bench/results/frame_cost.json and frame_cost_wfs_field.json (bench/bench_frame_cost.py)"
# (binning, oversampling, sensing oversampling): (CPU ms per frame, CPU s per case, CPU s per
# calibration, cold), measured by bench/bench_frame_cost.py on one thread (the thin-plate
# mirror): the sampled field's (o, o) on an idle machine (frame_cost.json); SOUL's 2.1" field's
# (o, 3) as those times the ratio 2.1"/0" the bench measured side by side in one run with the
# other core busy (frame_cost_wfs_field.json: 2.0-2.5x per frame at o = 2, 6x at o = 1; at o >= 3
# the field needs no finer pupil and the two agree within the run's +-10 %).  Oversampling 1
# only up to 90 modes.
_MEASURED = {
    (3, 1, 1): (2.9, 0.24, 2.7),
    (4, 1, 1): (2.5, 0.25, 2.2),
    (1, 2, 2): (8.8, 0.92, 7.9),
    (2, 2, 2): (7.0, 0.95, 4.0),
    (3, 2, 2): (7.0, 0.9, 3.2),
    (4, 2, 2): (7.3, 0.81, 2.8),
    (1, 3, 3): (17.0, 3.2, 16.0),
    (2, 3, 3): (15.0, 2.9, 7.4),
    (3, 3, 3): (15.0, 3.2, 3.9),
    (4, 3, 3): (14.0, 3.3, 2.9),
    (1, 4, 4): (25.0, 5.3, 25.0),
    (2, 4, 4): (23.0, 5.3, 13.0),
    (3, 4, 4): (23.0, 5.0, 6.0),
    (4, 4, 4): (27.0, 4.6, 4.2),
    (3, 1, 3): (17.7, 0.33, 6.0),
    (4, 1, 3): (14.9, 0.49, 3.8),
    (1, 2, 3): (17.7, 0.91, 15.9),
    (2, 2, 3): (16.0, 0.94, 7.6),
    (3, 2, 3): (17.6, 0.99, 5.5),
    (4, 2, 3): (17.5, 0.68, 3.8),
}
FRAME_MS = {k: v[0] for k, v in _MEASURED.items()}
CASE_FIXED_S = {k: v[1] for k, v in _MEASURED.items()}
CALIBRATION_S = {k: v[2] for k, v in _MEASURED.items()}
MEASURED_OVERSAMPLING = 4  # the finest the bench measures


def measured_cost(table: dict, binning: int, oversampling: int, sensing: int) -> float | None:
    """``table``'s cost for a binning, oversampling and sensing oversampling: measured, else a
    loop at the sensing oversampling (at most the measured 4, the FFT's area scaled above it);
    None when the loop's own sampling is not measured (a case refused at once: o = 1 above 90
    modes)."""
    if (binning, oversampling, sensing) in table:
        return table[binning, oversampling, sensing]
    if (binning, oversampling, oversampling) not in table:
        return None
    top = min(sensing, MEASURED_OVERSAMPLING)
    base = table.get((binning, top, top))
    return None if base is None else base * (sensing / top) ** 2


PARALLEL_EFFICIENCY = 0.82  # bench/results/sweep.json: speed-up 1.64 on 2 workers
CONFIRM_ABOVE_S = 3600.0  # estimated CPU time above which a terminal is asked before the sweep starts


@dataclass(frozen=True)
class Estimate:
    cases: int  # to run
    frames: int
    calibrations: int  # distinct set-ups
    cpu_seconds: float  # cases and calibrations, one thread
    workers: int | None  # None: the scheduler's

    @property
    def wall_seconds(self) -> float | None:
        if self.workers is None:
            return None
        return self.cpu_seconds / self.workers / (PARALLEL_EFFICIENCY if self.workers > 1 else 1.0)

    def text(self) -> str:
        wall = self.wall_seconds
        where = (
            f"about {duration_text(wall)} on {self.workers} worker{'s' if self.workers != 1 else ''}"
            if wall is not None
            else "divided by the scheduler's workers"
        )
        return (
            f"estimate: {self.cases} case{'s' if self.cases != 1 else ''}, {self.frames:,} frames, {self.calibrations} "
            f"calibration{'s' if self.calibrations != 1 else ''}: {duration_text(self.cpu_seconds)} of CPU, {where}"
        )

    def as_json(self) -> dict:
        return {
            "cases": self.cases,
            "frames": self.frames,
            "calibrations": self.calibrations,
            "cpu_seconds": self.cpu_seconds,
            "workers": self.workers,
            "wall_seconds": self.wall_seconds,
            "source": SOURCE,
        }


def duration_text(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    if seconds < 48 * 3600:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.1f} days"


@lru_cache(maxsize=4096)
def _observation(magnitude, binning, frame_rate, tt_control):
    case = {
        k: v
        for k, v in (("magnitude", magnitude), ("binning", binning), ("frame_rate", frame_rate), ("tt_control", tt_control))
        if v is not None
    }
    try:
        return observation_for(case)
    except InputError:
        return None  # the case fails at once: no cost


def case_cost(case: dict) -> tuple[int, float, tuple | None]:
    """(frames, CPU seconds, calibration key) of one case."""
    p = {**DEFAULTS, **case}
    obs = _observation(case["magnitude"], case.get("binning"), case.get("frame_rate"), case.get("tt_control"))
    sensing = (
        _sensing_oversampling(obs.binning, obs.modulation_lambda_over_d, p["oversampling"], p["wfs_field"]) if obs is not None else None
    )
    key = (obs.binning, p["oversampling"], sensing) if obs is not None and sensing is not None else None
    frame_ms = measured_cost(FRAME_MS, *key) if key is not None else None
    if obs is None or key is None or frame_ms is None:
        return 0, 0.0, None
    rate = obs.frame_rate_hz
    n = max(1, round(p["duration"] * rate))
    if p["gain_method"] != "default":
        period = max(1, round(optimisation_period_s(p["duration"], obs) * rate))
        n_close = closing_frames(rate) + period // 2  # stretched to an update boundary: half a period on average
        settle = round(evaluation_settle_s(period / rate, OPTIMISER_OGTL) * rate)  # as ``optimize`` settles each evaluation
        evaluation = 2 * (closing_frames(rate) + settle + n)  # before and after, paired, OGTL settling in each
        if p["gain_method"] == "mgm":
            n = n_close + OGTL_SETTLING_PERIODS * period + 3 * n + evaluation
        else:
            scan = (len(gain_groups(obs.modes)) * (TRIAL_VALUES + 1) + 1) * max(1, round(default_sequence_s(obs) * rate))
            n = n_close + OGTL_SETTLING_PERIODS * period + 2 * n + scan + evaluation
    fixed = measured_cost(CASE_FIXED_S, *key) or 0.0
    return n, fixed + n * frame_ms / 1e3, (*key, obs.modes, obs.modulation_lambda_over_d, p["wfs_field"])


@lru_cache(maxsize=4096)
def _sensing_oversampling(binning: int, modulation: float, oversampling: int, field: float) -> int | None:
    """The pyramid's sensing oversampling for a case (None: the configuration is refused)."""
    try:
        config = PyramidConfig(binning, modulation, oversampling=oversampling, field_of_view_arcsec=field)
    except InputError:
        return None
    return config.sensing_oversampling


def estimate(cases, workers: int | None) -> Estimate:
    """The estimate of running ``cases`` on ``workers`` (None: a scheduler's)."""
    frames, cpu, setups = 0, 0.0, set()
    for case in cases:
        n, seconds, setup = case_cost(case)
        frames += n
        cpu += seconds
        if setup is not None and setup not in setups:
            setups.add(setup)
            cpu += measured_cost(CALIBRATION_S, *setup[:3]) or 0.0
    return Estimate(len(cases), frames, len(setups), cpu, workers)


def needs_confirmation(e: Estimate) -> bool:
    return math.isfinite(e.cpu_seconds) and e.cpu_seconds > CONFIRM_ABOVE_S
