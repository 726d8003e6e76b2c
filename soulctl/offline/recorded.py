"""What a record says of its loop, for the analyses that model it (`telemetry identify`,
offline MGM, `telemetry psd`): each mode's controller, the structural resonance, the sensor
and the pupil that turns Tip/Tilt nm into mas.  One rule each (docs/telemetry-formats.md,
"What the analyses take from a record"):

* **Controller.** A soulctl record's: its run description's filters.  Another system's: the
  time filters it records (AOT ``time_filter_num/den``, the IIR keywords of an LBT
  reconstructor), a leading pure delay of the controller added to the loop delay in the
  models; integrators at the recorded gains only where it records none, and said so.
* **Structural resonance** (LBT's 127 Hz): a soulctl record's configuration; else LBT's model
  where the record's corrector is LBT's adaptive secondary; none otherwise.  ``structure``
  "lbt" or "none" overrides either.
* **Sensor**: the record's (``schema.SENSORS``): the optical-gain model follows from it
  (``offline.mgm``): the pyramid's model for a pyramid, 1 for a Shack-Hartmann or a quad cell.
* **Pupil**: the record's telescope (diameter, obstruction); LBT's where it states none, said so.

The rate of a record and of a configuration agree within ``RATE_TOLERANCE`` (a rate measured
from time stamps differs from the nominal one by ~1e-4); the record's rate is used.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from ..control.filters import Filter, filter_of_coefficients
from ..control.gains import unit_loops
from ..control.structure import StructuralResonance, sampled_coefficients, sampled_structure
from ..errors import InputError
from ..optics.pupil import LBT_DIAMETER_M
from ..run_config import RunConfig
from ..telemetry.analysis import nm_per_mas_of
from ..telemetry.schema import TelemetryReader

STRUCTURE_CHOICES = ("auto", "lbt", "none")  # --structure: the record's rule, LBT's 127 Hz model, none
RATE_TOLERANCE = 1e-3  # relative: a record's rate (measured from time stamps) against a configuration's


@dataclass(frozen=True)
class RecordedLoop:
    """A record's loop as the models see it (see the module)."""

    rate_hz: float
    filters: tuple[Filter, ...]  # unit gain, one per mode
    controller_delay: int  # frames of pure delay in the controller (added to the loop delay in the models)
    structure: StructuralResonance | None  # as the frame rate samples it
    sensor: str
    nm_per_mas: float  # nm RMS of the unit-RMS Tip mode per mas of tilt on the record's pupil
    diameter_m: float  # the record's pupil (LBT's when it states none)
    notes: tuple[str, ...] = ()

    @property
    def structure_ba(self) -> tuple | None:
        """(b, a) of the resonance at the record's rate, None without one."""
        return sampled_coefficients(self.structure, self.rate_hz)

    def model_delay(self, delay_frames: float) -> float:
        """The delay of the open loop's model: the loop's and the controller's pure delay."""
        return delay_frames + self.controller_delay


def checked_rate(record_hz: float, configured_hz: float, path: str | Path, what: str = "the record") -> tuple[float, str | None]:
    """The rate of a record (or of what was identified from one: ``what``) when it is the
    configuration's within RATE_TOLERANCE (a note when they differ at all), else InputError
    naming both."""
    if abs(record_hz - configured_hz) > RATE_TOLERANCE * configured_hz:
        where = f"telemetry file {path}" if what == "the record" else str(path)
        raise InputError(
            f"{where}: {what}'s rate ({record_hz:.6g} Hz) is not its configuration's ({configured_hz:.6g} Hz): "
            f"they must agree within {RATE_TOLERANCE:g} (relative)"
        )
    if record_hz == configured_hz:
        return record_hz, None
    return record_hz, f"{what}'s rate {record_hz:.6g} Hz used (the configuration's is {configured_hz:.6g} Hz)"


def recorded_loop(tm: TelemetryReader, description: RunConfig | None, n_modes: int, structure: str = "auto") -> RecordedLoop:
    """The loop of the record ``tm`` (see the module); ``description`` its soulctl run (None for
    another system's record); ``structure`` one of STRUCTURE_CHOICES."""
    if structure not in STRUCTURE_CHOICES:
        raise InputError(f"--resonance must be one of {', '.join(STRUCTURE_CHOICES)}, got {structure!r}")
    rate = float(tm.attribute("rate_hz"))
    notes: list[str] = []
    if description is not None:
        rate, note = checked_rate(rate, description.observation.frame_rate_hz, tm.path)
        notes += [note] if note else []
        filters, delay = list(unit_loops(description.observation, None, description.controller.forgetting, n_modes)[0]), 0
        resonance = description.structure
    else:
        filters, delay = _recorded_filters(tm, n_modes, notes)
        corrector = tm.attribute("corrector", None) or "unknown"
        resonance = StructuralResonance() if corrector == "lbt-adaptive-secondary" else None
        if structure == "auto":
            notes.append(f"structural resonance: {'LBT 127 Hz model' if resonance else 'none'} (the record's corrector: {corrector})")
    if structure != "auto":
        resonance = StructuralResonance() if structure == "lbt" else None
        notes.append(f"structural resonance: {'LBT 127 Hz model' if resonance else 'none'} (--resonance {structure})")
    sampled = sampled_structure(resonance, rate)
    sensor = tm.attribute("sensor", None) or ("pyramid" if description is not None else "unknown")
    diameter = tm.attribute("telescope_diameter_m", None) or LBT_DIAMETER_M
    return RecordedLoop(rate, tuple(filters), delay, sampled, sensor, _scale(tm, notes), diameter, tuple(notes))


def _scale(tm: TelemetryReader, notes: list[str]) -> float:
    scale, note = nm_per_mas_of(tm)
    notes += [note] if note else []
    return scale


def _recorded_filters(tm: TelemetryReader, n_modes: int, notes: list[str]) -> tuple[list[Filter], int]:
    """The unit filters of the record's time filters, and the controller's common pure delay."""
    if not (tm.has("controller_num") and tm.has("controller_den")):
        notes.append("the record states no controller: integrators at the recorded gains assumed")
        return [Filter.integrator(1.0)] * n_modes, 0
    num, den = tm.read("controller_num"), tm.read("controller_den")
    pairs = [filter_of_coefficients(b, a) for b, a in zip(num, den)]
    delays = {n for _, n in pairs}
    if len(delays) > 1:
        raise InputError(f"telemetry file {tm.path}: its controllers' pure delays differ between modes ({sorted(delays)} frames)")
    delay = delays.pop()
    if delay:
        notes.append(f"the recorded controller holds a pure delay of {delay} frame(s): added to the loop delay in the models")
    return [h for h, _ in pairs], delay
