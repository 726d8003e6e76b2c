"""SOULCTL_QUICK: every command at the smallest cost that still runs it, for the README's
doc test (tests/test_readme.py runs every example in CI with it set).

With ``SOULCTL_QUICK=1`` in the environment, the simulated runs of `loop run`, `optimize
gains`, `sweep` and `optics gains` keep their command line but:

- the pyramid reads the field its pupil's sampling gives (``--wfs-field 0``), unless the
  command line gives a field: about half a frame's cost, another sensor than SOUL's;
- a run is at most ``MAX_DURATION_S`` of simulated time, a sweep's case ``SWEEP_DURATION_S``;
- `optimize gains` updates at the shortest period MGM and OGTL accept, optimises for one period,
  measures ``WINDOWS`` windows of ``MEASURE_FRAMES`` frames and scans trial-and-error sequences
  of ``SEQUENCE_FRAMES`` frames, where the command line leaves them to their defaults;
- `optics gains` averages one residual screen.

Each command that is changed says so on stderr, once.  Its figures are a smoke test's, not
SOUL's: nothing else reads the variable.
"""

from __future__ import annotations

import os
import sys

ENV = "SOULCTL_QUICK"
FIELD_ARCSEC = 0.0
MAX_DURATION_S = 1.0
SWEEP_DURATION_S = 0.1
WINDOWS = 2
MEASURE_FRAMES = 60
SEQUENCE_FRAMES = 12
SCREENS = 1


def active() -> bool:
    """Whether SOULCTL_QUICK is set (to anything but '' or '0')."""
    return os.environ.get(ENV, "") not in ("", "0")


def notice(what: str) -> None:
    """One line on stderr: what SOULCTL_QUICK changed in this command."""
    print(f"soulctl: {ENV} is set: {what} (a smoke test's figures, not SOUL's)", file=sys.stderr)


def run_overrides(overrides: dict) -> dict:
    """A run description's overrides with the quick field where the command line gives none
    (``run.wfs_field_arcsec``); the duration is capped after resolution (``cap_duration``)."""
    return {"run.wfs_field_arcsec": FIELD_ARCSEC} | overrides


def sweep_case(case: dict, default_duration_s: float) -> dict:
    """A sweep's case with the quick field unless the grid gives one, SWEEP_DURATION_S at most."""
    return {"wfs_field": FIELD_ARCSEC} | case | {"duration": min(case.get("duration", default_duration_s), SWEEP_DURATION_S)}


def cap_duration(duration_s: float) -> float:
    """A run's simulated time, at most MAX_DURATION_S."""
    return min(duration_s, MAX_DURATION_S)
