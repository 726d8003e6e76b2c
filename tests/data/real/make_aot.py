"""Translators of the real records in this folder to AOT FITS (the AO Telemetry standard), with
aotpy only: what a user of another AO system writes to run soulctl on its records.  They are
independent of soulctl's own AOT writer, so that the tests read files soulctl did not write.

    python tests/data/real/make_aot.py OUT_DIR      # writes OUT_DIR/keck_strap_n0088.fits, ...

What each record is, and where each number comes from: README.md beside this file.
"""

from __future__ import annotations

import datetime
import math
import sys
from pathlib import Path

import aotpy
import numpy as np

HERE = Path(__file__).resolve().parent
ARCSEC_RAD = math.pi / (180 * 3600)


def nm_per_arcsec_tilt(diameter_m: float) -> float:
    """nm RMS of the unit-RMS Tip mode per arcsec of wavefront tilt on an unobstructed circular
    pupil of this diameter: the ramp x tilt has RMS(x) = D/4 (Noll 1976, Z2 = 2 rho cos theta)."""
    return diameter_m / 4 * ARCSEC_RAD * 1e9


def _image(name: str, data, unit: str | None = None, time=None) -> aotpy.Image:
    return aotpy.Image(name, np.ascontiguousarray(data, dtype=np.float32), unit=unit, time=time)


def _tip_tilt_loop(uid, measurements, commands, gain, den, rate, time, scale, telescope, sensor_uid, corrector_uid):
    """A Tip/Tilt loop: one 2-D sub-aperture measuring x and y (a quad cell is a 1 x 1
    Shack-Hartmann in AOT), modal commands, the time filter num / den in powers of z^-1."""
    star = aotpy.NaturalGuideStar("NGS")
    wfs = aotpy.ShackHartmann(
        uid=sensor_uid,
        source=star,
        n_valid_subapertures=1,
        measurements=_image("TT MEASUREMENTS", np.asarray(measurements)[:, :, None], "arcsec", time),
    )
    mirror = aotpy.TipTiltMirror(uid=corrector_uid, telescope=telescope)
    loop = aotpy.ControlLoop(uid=uid, input_sensor=wfs, commanded_corrector=mirror, time=time, closed=True)
    loop.framerate = rate
    loop.modal_coefficients = _image("TT COMMANDS", np.asarray(commands) * scale, "nm", time)
    loop.measurements_to_modes = _image("TT MEASUREMENTS TO MODES", np.eye(2)[:, :, None] * scale, "nm/arcsec")
    loop.time_filter_num = aotpy.Image("TIME FILTER NUM", np.full((2, 1), gain))
    loop.time_filter_den = aotpy.Image("TIME FILTER DEN", np.tile(np.asarray(den, dtype=float), (2, 1)))
    return star, wfs, mirror, loop


def keck_strap(out: Path) -> Path:
    """Keck II LGS AO, the down-Tip/Tilt loop on STRAP (a 4-APD quad cell), NIRC2 frame n0088:
    centroids in arcsec, commands in the centroids' unit; 1000 Hz; the controller
    c(k) = 0.6 c(k-1) + 0.32 c(k-2) + 0.08 c(k-3) + 0.1 s(k) (README.md)."""
    folder = HERE / "keck_strap_n0088"
    centroids = np.load(folder / "Centroid_n0088.npy").astype(np.float64)
    commands = np.load(folder / "Commands_n0088.npy").astype(np.float64)
    diameter = 10.0
    system = aotpy.AOSystem(ao_mode="LTAO", name="Keck II LGS AO, down Tip/Tilt loop (STRAP), NIRC2 n0088")
    system.main_telescope = aotpy.MainTelescope(uid="Keck II", enclosing_diameter=diameter)
    time = aotpy.Time("TT LOOP TIME", frame_numbers=list(range(len(centroids))))
    den = [1.0, -0.6, -0.32, -0.08]
    parts = _tip_tilt_loop(
        "DTT LOOP", centroids, commands, 0.1, den, 1000.0, time, nm_per_arcsec_tilt(diameter), system.main_telescope, "STRAP", "DTT"
    )
    return _write(system, parts, out / "keck_strap_n0088.fits")


def arte_downtiptilt(out: Path) -> Path:
    """The 100-frame Tip/Tilt snapshot of arte's tests (system not documented; units unknown,
    kept as they are: 1 unit = 1 'nm'); its rate is only in its time stamps (README.md)."""
    data = np.load(HERE / "arte_downtiptilt" / "downtiptilt.npz")
    slopes, commands = data["TTslope"], data["DTTMirrorCommand"]
    t_ns = data["rawtimestamp"]
    start = datetime.datetime.fromtimestamp(t_ns[0] * 1e-9, datetime.UTC)
    system = aotpy.AOSystem(ao_mode="SCAO", name="arte test snapshot 20240404_024500 downtiptilt", date_beginning=start)
    system.main_telescope = aotpy.MainTelescope(uid="not documented")
    time = aotpy.Time("TT LOOP TIME", timestamps=((t_ns - t_ns[0]) * 1e-9).tolist())
    parts = _tip_tilt_loop("DTT LOOP", slopes, commands, 0.05, [1.0, -1.0], None, time, 1.0, system.main_telescope, "TT sensor", "DTT")
    wfs = parts[1]
    wfs.measurements.unit = None  # not documented
    parts[3].modal_coefficients.unit = None
    return _write(system, parts, out / "arte_downtiptilt.fits")


def _write(system: aotpy.AOSystem, parts, path: Path) -> Path:
    star, wfs, mirror, loop = parts
    system.sources, system.wavefront_sensors, system.wavefront_correctors, system.loops = [star], [wfs], [mirror], [loop]
    system.write_to_file(str(path), overwrite=True)
    return path


RECORDS = {"keck_strap_n0088": keck_strap, "arte_downtiptilt": arte_downtiptilt}


def write_all(out: Path) -> dict[str, Path]:
    """Every record as AOT FITS in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    return {name: make(out) for name, make in RECORDS.items()}


if __name__ == "__main__":
    for name, path in write_all(Path(sys.argv[1] if len(sys.argv) > 1 else ".")).items():
        print(f"{name}: {path}")
