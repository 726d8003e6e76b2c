"""Loop telemetry as HDF5 (h5py): what `loop run --telemetry` writes and `optimize gains` reads.

HDF5 because the record is several large arrays of different shapes plus a nested
configuration: one file with named, typed, chunked and compressed datasets and attributes,
read partially by h5py, MATLAB, IDL, Julia or `h5dump` without loading everything, and
extended chunk by chunk while the loop runs (``stream.Hdf5Writer``: constant memory, any length).

Layout (rows are recorded frames; every dataset's "unit" attribute names its unit):
    /slopes            (frames, n_slopes) float32   slopes s(k) from the slope computer (times k)
    /measured_modes    (frames, n_modes)  float32   R s(k), nm
    /commands          (frames, n_actuators) float32  c(k) = Sigma zeta(k), nm
    /command_modes     (frames, n_modes)  float32   M^-1 c(k), nm
    /mirror_modes      (frames, n_modes)  float32   the mirror during frame k (delayed), nm
    /residual_modes    (frames, n_modes)  float32   the simulation's true residual, nm
    /disturbance_modes (frames, n_modes)  float32   the simulation's true disturbance, nm
    /residual_rms_nm   (frames,)          float64
    /frame_counter     (frames,)          int64     the loop's frame number k of each row
    /frame_time_s      (frames,)          float64   k / frame rate
    /sensitivity       (frames,)          float64   slope sensitivity k during frame k
    /flux              (frames,)          float64   detected electrons in frame k
    /gains             (n_modes,)         float64   per-mode gains (Delta of each mode) at the end
    /reconstructor     (n_modes, n_slopes) float32  R: the modes (nm) of the slopes
    /modes_to_commands (n_actuators, n_modes) float32  M: the actuator commands of each mode
    /controller_num    (n_modes, num_terms) float64  each mode's unit-gain time filter, numerator and
    /controller_den    (n_modes, den_terms) float64  denominator in powers of z^-1 (c = g num/den m)
    /gain_history/frames (changes,)       int64     first frame of each gain vector
    /gain_history/gains  (changes, n_modes) float64 the gain vectors in force from those frames
    /aux/<task>/<field> (updates, ...)    float64   auxiliary loops' records (e.g. /aux/ogtl/
                                                    sensitivity, /aux/mgm/gains, /aux/metrics/
                                                    strehl_estimate), /aux/<task>/frame the
                                                    first frame after each update
    attributes: rate_hz, delay_frames, n_modes, sensor, corrector, telescope,
                telescope_diameter_m, telescope_obstruction_m (what the loop is: LBT's
                pyramid and adaptive secondary), soulctl_version, schema_version (2; files
                without it are version 1 and read alike), status (complete | partial |
                writing), partial_reason, telemetry_every (one frame in N recorded),
                diverged_at (-1 if not), configuration (JSON: observation, atmosphere,
                gains, seed, ...), run_description (TOML: the resolved run description;
                `loop run --config this.h5` runs the same loop again)
The per-frame fields are those of `--telemetry-fields` (default: all but slopes and
commands).  A file is written under a temporary name and renamed when the run ends: complete,
or partial (interrupted, diverged, an error) with every frame up to the last one recorded.

``schema.TELEMETRY_SCHEMA`` is this layout as a table - kinds, dtypes, shapes, units and the
range of every value - with the relations between fields (``RELATIONS``); every reader holds a
file to it (``schema.TelemetryReader``) and a test holds this docstring to it.

Offline MGM (`optimize gains --telemetry`) needs measured_modes, command_modes, gains and the
rate_hz and delay_frames attributes; it uses sensitivity, gain_history, /aux/ogtl and the
configuration when present, and reads only the rows of its window (see ``offline.mgm``).
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from .. import __version__
from ..files import atomic_write
from ..ranges import TELEMETRY_SCHEMA_VERSION
from .schema import store


def write_telemetry(
    path: str | Path, arrays: dict[str, np.ndarray], attributes: dict, configuration: dict, immediate: bool = False
) -> None:
    """A whole telemetry record at once (``telemetry convert``; tests), written atomically."""

    def write(tmp: str) -> None:
        with h5py.File(tmp, "w") as f:
            defaults = {"schema_version": TELEMETRY_SCHEMA_VERSION, "status": "complete", "soulctl_version": __version__}
            store(f, arrays, defaults | attributes | {"configuration": configuration})

    atomic_write(path, write, immediate=immediate)
