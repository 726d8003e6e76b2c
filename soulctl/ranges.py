"""One home for the accepted range of every number a user gives soulctl, on the command line,
in an observation/vibration/grid file or through the Python API.

Each range is a ``Range``: ``check(value, name)`` returns the value or raises an InputError
that names the input in the user's terms, the accepted range and the value with enough digits
to show why (``--wind 100.0001`` is reported as 100.0001, not 100).  Command-line options,
TOML readers and dataclasses all check against the same objects, so that a value accepted by
one command is accepted by every other.

Numbers are read as Python reads them: Unicode decimal digits (e.g. full-width "１３") are the
same digits as ASCII ones, and "1_000" is 1000; NaN and infinities are never accepted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from .errors import InputError


def number_text(value) -> str:
    """A value as an error message shows it: floats with up to 10 significant digits."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, int):
        text = str(value)
        return text if len(text) <= 24 else f"{text[:12]}...({len(text.lstrip('-'))} digits)"
    return format(value, ".10g")


@dataclass(frozen=True)
class Range:
    """An interval of accepted values, closed unless ``lo_open``/``hi_open``; ``integer`` for
    counts and seeds (bools are never numbers)."""

    lo: float
    hi: float
    unit: str = ""
    lo_open: bool = False
    hi_open: bool = False
    integer: bool = False

    def text(self) -> str:
        """The range as messages and --help show it, e.g. '0..100 m/s (> 0)'."""
        lo, hi = number_text(self.lo), number_text(self.hi)
        if self.integer and self.hi >= 2**62:
            hi = "2^63-1"
        bounds = [f"> {lo}"] if self.lo_open else []
        bounds += [f"< {hi}"] if self.hi_open else []
        return f"{lo}..{hi}" + (f" {self.unit}" if self.unit else "") + (f" ({', '.join(bounds)})" if bounds else "")

    def contains(self, value) -> bool:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return False
        if isinstance(value, float) and not (math.isfinite(value) and (value.is_integer() or not self.integer)):
            return False
        above = value > self.lo if self.lo_open else value >= self.lo
        below = value < self.hi if self.hi_open else value <= self.hi
        return above and below

    def check(self, value, name: str):
        """``value`` if it is in the range (ints stay ints), else InputError naming ``name``."""
        if not self.contains(value):
            is_number = (
                isinstance(value, int)
                and not isinstance(value, bool)
                or (isinstance(value, float) and (not self.integer or (math.isfinite(value) and value.is_integer())))
            )
            kind = "" if is_number else ("an integer " if self.integer else "a number ")
            raise InputError(f"{name} must be {kind}in {self.text()}, got {number_text(value)}")
        return int(value) if self.integer else value + 0.0  # -0.0 -> 0.0

    def parse(self, text: str, name: str):
        """A command-line string checked against the range (see the module for what is a number)."""
        try:
            value = int(text) if self.integer else float(text)
        except (TypeError, ValueError):
            kind = "an integer" if self.integer else "a number"
            raise InputError(f"{name} must be {kind} in {self.text()}, got '{text}'") from None
        return self.check(value, name)


# --- the guide star and the observation (soulctl.observation) -------------------------------
# The magnitude's range is the look-up table's (tables/magnitude_lut.csv): tables.magnitude_range.
FRAME_RATE_HZ = Range(10.0, 2000.0, "Hz")
BINNING = Range(1, 4, integer=True)  # the detector binnings of the look-up table (observation.BINNINGS)
MODULATION_LAMBDA_OVER_D = Range(0.0, 20.0, "lambda/D")
# Controlled modes: Tip and Tilt at least (their IIR pair), at most the LBT672's 671 modes
# (672 actuators less piston; checked against the modal basis in the tests).
MODES = Range(2, 671, integer=True)
# WFS zero point: the table's 2.647e8 ph/s per binning-1 sub-aperture, within a factor 1000.
ZERO_POINT_PH_S = Range(2.647e5, 2.647e11, "ph/s per sub-aperture")
DELAY_TERM_MS = Range(0.0, 10.0, "ms")  # each term of the delay model (readout, computation, ASM); SOUL: 0.2-1.2 ms

# --- the atmosphere and the run (loop run, optimize gains, sweep) ---------------------------
SEEING_ARCSEC = Range(0.05, 10.0, "arcsec")
# mis-registration of the adaptive secondary on the pyramid (optics.registration): beyond a
# pitch or a few degrees the interaction matrix no longer describes the mirror at all
SHIFT_PITCH = Range(-2.0, 2.0, "actuator pitches")
ROTATION_DEG = Range(-10.0, 10.0, "deg")
MAGNIFICATION = Range(0.8, 1.2)
# non-common-path aberrations (optics.ncpa): on-sky instruments carry 10-300 nm
NCPA_RMS_NM = Range(0.0, 1000.0, "nm")
NCPA_EXPONENT = Range(0.0, 4.0)  # of the PSD's power law
NCPA_OFFSET_FRACTION = Range(0.0, 1.0)  # of the offsets the RTC applies
# the interaction matrix measured at a finite flux (optics.calibration_noise)
CALIBRATION_PHOTONS = Range(1.0, 1e12, "photons per frame")
CALIBRATION_FRAMES = Range(1, 10_000, integer=True)
WIND_M_S = Range(0.0, 100.0, "m/s", lo_open=True)  # the effective (5/3-moment) wind of the profile
OUTER_SCALE_M = Range(0.5, 1e4, "m")
DURATION_S = Range(0.0, 600.0, "s", lo_open=True)
OVERSAMPLING = Range(1, 4, integer=True)
WFS_FIELD_OF_VIEW_ARCSEC = Range(0.0, 4.0, "arcsec")  # the pyramid's simulated field (0: as sampled, no stop)
SEED = Range(0, 2**63 - 1, integer=True)  # numpy's generators take non-negative seeds
LOOP_GAIN = Range(0.0, 10.0)  # a modal gain of the RTC (the stability check comes after)
DESIGNED_GAIN = Range(0.0, 10.0, lo_open=True)  # a roots table's gain column (filter design --out)
FORGETTING = Range(0.0, 1.0)  # of the leaky integrators
FRACTION = Range(0.0, 1.0)  # optics gains --controlled-fraction
SCREENS = Range(1, 64, integer=True)  # optics gains --screens (~10 s each at 40x40, 500 modes)

# --- telemetry files (soulctl/telemetry/schema.py) -----------------------------------
MODAL_NM = Range(-1e6, 1e6, "nm")  # a mode or actuator, 1 mm: far beyond any mirror's stroke
RMS_NM = Range(0.0, 1e6, "nm")
FRAME_TIME_S = Range(0.0, 1e7, "s")
SENSITIVITY = Range(0.05, 20.0)  # the slope sensitivity k, as OGTL clamps it
FRAME_INDEX = Range(0, 2**63 - 1, integer=True)
RECORD_RATE_HZ = Range(0.0, 1e5, "Hz", lo_open=True)  # a record's loop rate, any system's (a simulation's: FRAME_RATE_HZ)
RECORD_MODES = Range(1, 100_000, integer=True)  # the modes a record holds, any system's (a Tip/Tilt loop: 2)
TELESCOPE_M = Range(0.0, 100.0, "m")  # a record's telescope diameter or central obstruction
DIVERGED_AT = Range(-1, 2**63 - 1, integer=True)  # -1: the loop did not diverge
OPTICAL_GAIN = Range(0.0, 2.0, lo_open=True)  # a modal optical gain gamma_i (optimize gains --chi-table)
TELEMETRY_SCHEMA_VERSION = 2  # 1: files of soulctl before streaming (no frame_counter, status); still read
SCHEMA_VERSION = Range(1, TELEMETRY_SCHEMA_VERSION, integer=True)
TELEMETRY_EVERY = Range(1, 100_000, integer=True)  # loop run --telemetry-every: record one frame in N

# --- auxiliary loops ------------------------------------------------------------------------
PERIOD_S = Range(0.0, 600.0, "s", lo_open=True)
OPTIMISATION_S = Range(0.0, 3600.0, "s", lo_open=True)  # optimize gains --duration
MEASURE_S = Range(0.0, 600.0, "s", lo_open=True)  # optimize gains --measure (before and after)
EVALUATION_WINDOWS = Range(1, 100, integer=True)  # optimize gains --windows (the paired evaluation's)
MIN_MEASURE_FRAMES = 20  # a measurement shorter than this has no meaningful jitter
SEQUENCE_S = Range(0.0, 60.0, "s", lo_open=True)  # one trial-and-error sequence
PROBE_MODE = Range(1, MODES.hi, integer=True)  # 1-based; at most the controlled modes (checked with the observation)
PROBE_AMPLITUDE_NM = Range(0.1, 1000.0, "nm")  # 0.1 nm: far below any noise, the lock-in sees nothing smaller
PROBE_FREQUENCY_HZ = Range(0.0, 1e3, "Hz", lo_open=True)  # and below the loop's Nyquist frequency (checked with the rate)
PROBE_MIN_CYCLES = 4  # the OGTL probe's period fits this many times in an update period

# --- sweeps -------------------------------------------------------------------------------
LOCAL_WORKERS_PER_CORE = 2  # sweep --workers: more processes than this per core only cost memory (~0.3 GB each)
WAIT_WORKERS_S = 60.0  # sweep --scheduler: how long a scheduler may be without workers (--wait-workers)
WAIT_WORKERS = Range(0.0, 86400.0, "s", lo_open=True)

# --- vibrations (tables/lbt_vibrations.toml, --vibrations) ----------------------------------
VIBRATION_FREQUENCY_HZ = Range(0.1, 1000.0, "Hz")
VIBRATION_DAMPING = Range(1e-4, 0.9)  # an underdamped oscillator; 1e-4 already rings for hours
VIBRATION_RMS_MAS = Range(0.0, 1000.0, "mas")  # per axis; on-sky lines are 1-30 mas

# --- control analysis and design (filter analyze | design) ----------------------------------
ANALYSIS_RATE_HZ = Range(1.0, 1e5, "Hz")
# Delay in frames: the characteristic polynomial's degree grows with it, and so does the cost
# of the analysis (~0.3 s at 50 frames); AO loops run with 1-5 frames.
DELAY_FRAMES = Range(0.0, 50.0, "frames")
ANALYSIS_GAIN = Range(1e-4, 1e3)  # below 1e-4 the closed-loop poles sit within 1e-9 of z = 1
OPTICAL_GAIN = Range(1e-3, 1e3)  # chi
ROOT_MODULUS = 10.0  # |zero| and |pole| of a controller given by its roots
MAX_CONTROLLERS = 16  # controllers compared side by side by one `filter analyze`
# The design's cost grows with the rate and the delay (the closed-loop polynomial of every
# candidate): ~5 s at 1700 Hz and 3.6 frames, ~90 s at 4000 Hz, ~6 min at 50 frames.
DESIGN_RATE_HZ = Range(100.0, FRAME_RATE_HZ.hi, "Hz")  # 13 Hz well below Nyquist, up to the fastest frame rate
DESIGN_DELAY_FRAMES = Range(0.0, 10.0, "frames")
MAX_DESIGN_RATES = 8
EPSILON = Range(0.0, 1.0, lo_open=True, hi_open=True)
NOISE_MAS = Range(0.0, 1e4, "mas")
ROOTS_RATE_TOLERANCE = 0.2  # a roots-table row applies within 20 % of its frame rate
