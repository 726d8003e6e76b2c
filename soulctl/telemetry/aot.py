"""Telemetry as AOT FITS, the AO Telemetry standard, through its package ``aotpy``.

Writing (`loop run --telemetry run.fits`, `telemetry convert`) maps soulctl's model onto the
standard's objects:

    soulctl field               AOT                                           unit in AOT
    rate_hz, delay_frames       ControlLoop.framerate, .delay                 Hz, frames
    slopes (frames, n_slopes)   Pyramid.measurements (t, 2, s_v): [sx.., sy..] normalised slope x k
    commands                    ControlLoop.commands (t, a_v)                 m (nm x 1e-9)
    command_modes (M^-1 c)      ControlLoop.modal_coefficients (t, m)         nm
    reconstructor R             ControlLoop.measurements_to_modes (m, 2, s_v) nm per slope unit
    modes_to_commands M         ControlLoop.modes_to_commands (a_v, m)        nm per nm
    gains                       ControlLoop.time_filter_num (m, 1), den (m, 2) = [1, -1]
    frame_counter, frame_time_s Time.frame_numbers, .timestamps (s from the run's start)
    modulation (lambda/D)       Pyramid.modulation = r lambda_WFS (m: the optical path of the
                                modulation tilt across the pupil) and keyword SOULMODL (lambda/D)

The standard has one per-frame modal slot (the modes sent to the corrector, as LBT's
Modes_<TN>.fits), so the other records - R s, the mirror's, residual and disturbance modes,
residual RMS, k, flux, the gain history, the auxiliary loops' records, the configuration and
the run description - go in extension HDUs without an EXTNAME that aotpy leaves alone
(aotpy refuses named images nothing references), each tagged by keyword SOULNAME; the status,
schema version and decimation are keywords of the primary header.

Reading (any AOT file, e.g. from aotpy's translators for ESO, Keck or PAPYRUS systems): the
first control loop and its input sensor (pyramid or Shack-Hartmann).  Where soulctl's own
HDUs are absent, R s is measurements_to_modes @ slopes, M^-1 c is modal_coefficients or
pinv(modes_to_commands) @ commands, and gains are the time filters' first numerators; commands
in m are converted to nm, modal quantities are taken as nm unless their unit is m.  A field
the file cannot give is absent from the model, and an analysis that needs it names it.
"""

from __future__ import annotations

import datetime
import json
import warnings
from pathlib import Path

import h5py
import numpy as np
from astropy.io import fits

from .. import blas
from ..control.filters import unit_coefficients
from ..errors import InputError
from ..files import atomic_write, input_file
from ..ranges import TELESCOPE_M
from .schema import LBT_SYSTEM, PER_FRAME, REQUIRED, Note, TelemetryReader, check_slope_pairs, nested

WFS_WAVELENGTH_M = 750e-9  # the pyramid's band centre (optics.pwfs.PyramidConfig.wavelength_m)
EXTRA_KEY = "SOULNAME"  # the keyword that names soulctl's own extension HDUs
TEXT_FIELDS = ("configuration", "run_description")
KEYWORDS = {  # primary-header keyword -> attribute
    "SOULVERS": "soulctl_version",
    "SOULSCHV": "schema_version",
    "SOULSTAT": "status",
    "SOULWHY": "partial_reason",
    "SOULEVRY": "telemetry_every",
    "SOULDIVF": "diverged_at",
    "SOULNMOD": "n_modes",
}
# kept exactly too: AOT's commands are float32 metres, its modal slot float32, its filters the gains times the unit filters
EXACT = ("commands", "command_modes", "controller_num", "controller_den")
AOT_FIELDS = (
    "slopes", "commands", "command_modes", "reconstructor", "modes_to_commands", "gains", "controller_num", "controller_den",
    "frame_counter", "frame_time_s",
)  # fmt: skip


def _aotpy():
    import aotpy  # imported when used: a second or so, and only FITS work needs it

    return aotpy


def _image(name: str, data, unit: str | None = None, time=None, dtype=np.float32):
    return _aotpy().Image(name, np.ascontiguousarray(data, dtype=dtype), unit=unit, time=time)


def _loop_objects(arrays: dict, attributes: dict, configuration: dict):
    """The AOT system of a record (see the module)."""
    aot = _aotpy()
    check_slope_pairs(arrays, "AOT FITS (measurements of 2 dimensions)")
    frames = np.asarray(arrays.get("frame_counter", np.arange(_frames(arrays))))
    rate, delay = attributes.get("rate_hz"), attributes.get("delay_frames")
    seconds = arrays.get("frame_time_s", None if rate is None else frames / rate)
    system = aot.AOSystem(ao_mode="SCAO", name="soulctl simulated loop", date_beginning=datetime.datetime.now(datetime.UTC))
    pupil = LBT_SYSTEM | {k: attributes[k] for k in ("telescope", "telescope_diameter_m", "telescope_obstruction_m") if k in attributes}
    system.main_telescope = aot.MainTelescope(
        uid=pupil["telescope"],
        enclosing_diameter=pupil["telescope_diameter_m"],
        inscribed_diameter=pupil["telescope_diameter_m"],
        obstruction_diameter=pupil["telescope_obstruction_m"],
    )
    timestamps = None if seconds is None else np.asarray(seconds, dtype=float).tolist()
    time = aot.Time(uid="LOOP TIME", timestamps=timestamps, frame_numbers=frames.astype(int).tolist())
    star = aot.NaturalGuideStar("NGS")
    n_slopes = _n_slopes(arrays)
    modulation = float(nested(configuration, "observation", "wfs", "modulation_lambda_over_d", number=True) or 0.0)
    slopes = arrays.get("slopes")
    measurements = None if slopes is None else _image("WFS SLOPES", np.reshape(slopes, (len(slopes), 2, -1)), "slope x k", time)
    if attributes.get("sensor", "pyramid") == "pyramid":
        wfs = aot.Pyramid(
            uid="PWFS",
            source=star,
            dimensions=2,
            n_sides=4,
            n_valid_subapertures=n_slopes // 2,
            modulation=modulation * WFS_WAVELENGTH_M,
            wavelength=WFS_WAVELENGTH_M,
            measurements=measurements,
        )
    else:  # a Shack-Hartmann (a quad cell: one sub-aperture)
        wfs = aot.ShackHartmann(uid="WFS", source=star, n_valid_subapertures=max(1, n_slopes // 2), measurements=measurements)
    if attributes.get("corrector") == "tip-tilt-mirror":
        mirror = aot.TipTiltMirror(uid="TTM", telescope=system.main_telescope)
    else:
        uid = "ASM" if attributes.get("corrector", "lbt-adaptive-secondary") == "lbt-adaptive-secondary" else "DM"
        mirror = aot.DeformableMirror(uid=uid, telescope=system.main_telescope, n_valid_actuators=_n_actuators(arrays))
    loop = aot.ControlLoop(uid="HO LOOP", input_sensor=wfs, commanded_corrector=mirror, time=time, closed=True)
    loop.framerate = None if rate is None else float(rate)
    loop.delay = None if delay is None else float(delay)
    _loop_arrays(loop, arrays, time)
    system.sources, system.wavefront_sensors, system.wavefront_correctors, system.loops = [star], [wfs], [mirror], [loop]
    system.metadata = [aot.Metadatum("SOULMODL", modulation, "pyramid modulation radius [lambda/D]")]
    system.metadata += [aot.Metadatum(k, attributes[a]) for k, a in KEYWORDS.items() if a in attributes]
    return system


def _loop_arrays(loop, arrays: dict, time) -> None:
    if "commands" in arrays:
        loop.commands = _image("DM COMMANDS", np.asarray(arrays["commands"]) * 1e-9, "m", time)
    if "command_modes" in arrays:
        loop.modal_coefficients = _image("MODAL COEFFICIENTS", arrays["command_modes"], "nm", time)
    if "reconstructor" in arrays:
        r = np.asarray(arrays["reconstructor"])
        loop.measurements_to_modes = _image("MEASUREMENTS TO MODES", r.reshape(r.shape[0], 2, -1), "nm")
    if "modes_to_commands" in arrays:
        loop.modes_to_commands = _image("MODES TO COMMANDS", arrays["modes_to_commands"])
    if "gains" in arrays:
        g = np.asarray(arrays["gains"], dtype=float)
        num, den = (arrays[k] if "controller_num" in arrays else None for k in ("controller_num", "controller_den"))
        if num is None or den is None:  # a record without its filters: integrators
            num, den = np.ones((len(g), 1)), np.tile([1.0, -1.0], (len(g), 1))
        loop.time_filter_num = _image("TIME FILTER NUM", g[:, None] * np.asarray(num), dtype=np.float64)
        loop.time_filter_den = _image("TIME FILTER DEN", den, dtype=np.float64)


def _frames(arrays: dict) -> int:
    """Rows of the per-frame records (0 without any)."""
    return next((len(v) for k, v in arrays.items() if k in PER_FRAME), 0)


def _n_slopes(arrays: dict) -> int:
    for name, axis in (("slopes", 1), ("reconstructor", 1)):
        if name in arrays:
            return int(np.shape(arrays[name])[axis])
    return 0


def _n_actuators(arrays: dict) -> int:
    for name, axis in (("commands", 1), ("modes_to_commands", 0)):
        if name in arrays:
            return int(np.shape(arrays[name])[axis])
    return 0


def write_aot(path: str | Path, arrays: dict, attributes: dict, configuration: dict, immediate: bool = False) -> None:
    """A record as an AOT FITS file (atomically), soulctl's other records in tagged HDUs."""
    from aotpy.io.fits import AOTFITSWriter

    system = _loop_objects(arrays, attributes, configuration)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        hdus = AOTFITSWriter(system).get_hdulist()
    for name, data in arrays.items():
        if name not in AOT_FIELDS or name in EXACT:
            hdus.append(tagged_hdu(name, np.asarray(data)))
    texts = {"configuration": json.dumps(configuration)} | {k: attributes[k] for k in TEXT_FIELDS[1:] if k in attributes}
    for name, text in texts.items():
        hdus.append(tagged_hdu(name, np.frombuffer(text.encode("utf-8"), dtype=np.uint8)))
    atomic_write(path, lambda tmp: hdus.writeto(tmp, overwrite=True), immediate=immediate)


def tagged_hdu(name: str, data: np.ndarray) -> fits.ImageHDU:
    """An extension HDU of soulctl's own record ``name`` (keyword SOULNAME, no EXTNAME)."""
    hdu = fits.ImageHDU(data if data.dtype.kind != "b" else data.astype(np.uint8))
    hdu.header[EXTRA_KEY] = name
    return hdu


def read_aot(path: str | Path, required: tuple[str, ...] = REQUIRED) -> TelemetryReader:
    """An AOT FITS file as soulctl's model (see the module); InputError naming what is wrong."""
    p = input_file(path, "telemetry file")
    if h5py.is_hdf5(p):
        raise InputError(f"telemetry file {path} is an HDF5 file named as FITS: name it .h5 to read it as soulctl's HDF5")
    aot = _aotpy()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            system = aot.AOSystem.read_from_file(str(p), memmap=False)
            with fits.open(p, memmap=False) as hdus:
                extras = {h.header[EXTRA_KEY]: np.asarray(h.data) for h in hdus if EXTRA_KEY in h.header}
                header = dict(hdus[0].header)
    except InputError:
        raise
    except Exception as e:  # noqa: BLE001 - astropy and aotpy raise many kinds for a bad file
        first = " ".join(str(e).split()).split(". ")[0][:160]  # the reason, without the readers' hints at their own options
        raise InputError(f"telemetry file {path} is not a readable AOT FITS file ({first})") from None
    loops = [loop for loop in system.loops if isinstance(loop, aot.ControlLoop)]
    if not loops:
        raise InputError(f"telemetry file {path}: the AOT file has no control loop")
    notes: list[Note] = []
    try:
        arrays, attributes = _model_of(loops[0], extras, header, notes)
        attributes |= _system_of(system, loops[0])
    except InputError as e:
        raise InputError(f"telemetry file {path}: {e}") from None
    except (ValueError, TypeError, IndexError, AttributeError, UnicodeDecodeError) as e:
        raise InputError(f"telemetry file {path}: cannot read the AOT loop's records ({' '.join(str(e).split())[:160]})") from None
    foreign = {} if "soulctl_version" in attributes else {"slopes_unit": _unit_of(loops[0].input_sensor)}
    return TelemetryReader.from_arrays(path, arrays, attributes, required, tuple(notes), **foreign)


def _unit_of(wfs) -> str:
    """The unit another system's file gives its measurements."""
    measurements = getattr(wfs, "measurements", None)
    return str(getattr(measurements, "unit", None) or "not stated")


def _model_of(loop, extras: dict, header: dict, notes: list[Note]) -> tuple[dict, dict]:
    """The model's arrays and attributes of an AOT control loop and soulctl's extra HDUs."""
    arrays: dict = {}
    attributes = {a: header[k] for k, a in KEYWORDS.items() if k in header}
    if loop.delay is not None:
        attributes["delay_frames"] = float(loop.delay)
    wfs = loop.input_sensor
    if wfs is not None and wfs.measurements is not None and wfs.measurements.data is not None:
        data = np.asarray(wfs.measurements.data)
        arrays["slopes"] = data.reshape(data.shape[0], -1)
    _add(arrays, "commands", loop.commands, scale_m=True)
    _add(arrays, "command_modes", loop.modal_coefficients, scale_m=True)
    _add(arrays, "modes_to_commands", loop.modes_to_commands)
    r = _data(loop.measurements_to_modes)
    if r is not None:
        arrays["reconstructor"] = r.reshape(r.shape[0], -1) * _to_nm(loop.measurements_to_modes)
    _time_arrays(arrays, loop.time)
    _derived(arrays)
    rate = _rate(loop, arrays, notes)
    if rate is not None:
        attributes["rate_hz"] = rate
    _controller(loop, arrays, notes)
    for name, data in extras.items():
        if name in TEXT_FIELDS:
            attributes[name] = bytes(data.astype(np.uint8)).decode("utf-8")
        else:
            arrays[name] = data
    if "gains" in arrays and "n_modes" not in attributes:
        attributes["n_modes"] = len(arrays["gains"])
    return arrays, attributes


def _rate(loop, arrays: dict, notes: list[Note]) -> float | None:
    """ControlLoop.framerate, else the rate of the time stamps (frames per second between rows)."""
    if loop.framerate is not None:
        return float(loop.framerate)
    t = arrays.get("frame_time_s")
    if t is None or len(t) < 3:
        notes.append(Note("rate_hz", "the AOT loop states no framerate and holds no time stamps to measure it"))
        return None
    frames = arrays["frame_counter"][-1] - arrays["frame_counter"][0] if "frame_counter" in arrays else len(t) - 1
    t = np.asarray(t, dtype=float)
    if not (np.all(np.isfinite(t)) and np.all(np.diff(t) > 0) and frames > 0):
        notes.append(Note("rate_hz", "the AOT loop states no framerate and its time stamps do not increase"))
        return None
    rate = float(frames / (t[-1] - t[0]))  # over the record (a median of steps is quantised by the stamps' resolution)
    notes.append(Note("rate_hz", f"rate {rate:.6g} Hz from the time stamps (the AOT loop states no framerate)"))
    return rate


def _n_modes(arrays: dict) -> int | None:
    for name in ("command_modes", "measured_modes", "reconstructor"):
        if name in arrays:
            return int(np.shape(arrays[name])[1 if name != "reconstructor" else 0])
    return None


def _controller(loop, arrays: dict, notes: list[Note]) -> None:
    """The time filters (AOT: one per mode, or one for all, H = sum b_i z^-i / sum a_j z^-j,
    "the first numerator is the loop gain") as the unit filters and the gains
    (``filters.unit_coefficients``); without a denominator, integrators."""
    num, den = _data(loop.time_filter_num), _data(loop.time_filter_den)
    if num is None or not num.size:
        notes.append(Note("controller_num", "the AOT loop states no time filter: neither the gains nor the controller are known"))
        return
    n_modes = _n_modes(arrays)
    num = np.asarray(num, dtype=float)
    if num.ndim == 1:  # one coefficient per mode, or one filter for all
        num = num[:, None] if n_modes is not None and len(num) == n_modes and n_modes > 1 else num[None, :]
    num = num.reshape(num.shape[0], -1)
    if den is None or not den.size:
        den = np.array([[1.0, -1.0]])
        notes.append(Note("controller_den", "the AOT loop states no time-filter denominator: integrators (1 - z^-1) taken"))
    den = np.asarray(den, dtype=float)
    den = den.reshape(den.shape[0], -1) if den.ndim > 1 else den[None, :]
    rows = n_modes or max(num.shape[0], den.shape[0])
    if num.shape[0] not in (1, rows) or den.shape[0] not in (1, rows):
        raise InputError(f"the time filters have {num.shape[0]} numerators and {den.shape[0]} denominators for {rows} modes")
    unit, unit_den, gains = unit_coefficients(np.repeat(num, rows // num.shape[0], axis=0), np.repeat(den, rows // den.shape[0], axis=0))
    arrays["gains"], arrays["controller_num"], arrays["controller_den"] = gains, unit, unit_den


def _system_of(system, loop) -> dict:
    """What the AOT file says of the loop: its sensor (a Shack-Hartmann of one sub-aperture is
    a quad cell), its corrector (a deformable mirror of a telescope named LBT is the adaptive
    secondary) and its telescope's pupil."""
    aot = _aotpy()
    wfs, corrector, telescope = loop.input_sensor, loop.commanded_corrector, system.main_telescope
    out: dict = {"sensor": "unknown", "corrector": "unknown"}
    if isinstance(wfs, aot.Pyramid):
        out["sensor"] = "pyramid"
    elif isinstance(wfs, aot.ShackHartmann):
        out["sensor"] = "quad-cell" if wfs.n_valid_subapertures == 1 else "shack-hartmann"
    name = str(getattr(telescope, "uid", "") or "")
    if isinstance(corrector, aot.TipTiltMirror):
        out["corrector"] = "tip-tilt-mirror"
    elif isinstance(corrector, aot.DeformableMirror):
        out["corrector"] = "lbt-adaptive-secondary" if "LBT" in name.upper() else "deformable-mirror"
    if name:
        out["telescope"] = name
    for key, field in (("telescope_diameter_m", "enclosing_diameter"), ("telescope_obstruction_m", "obstruction_diameter")):
        value = getattr(telescope, field, None)
        if value is not None and TELESCOPE_M.contains(value):
            out[key] = float(value)
    return out


def _data(image) -> np.ndarray | None:
    if image is None or image.data is None:
        return None
    data = np.asarray(image.data)
    return data.astype(data.dtype.newbyteorder("=")) if data.dtype.kind in "fiu" else data


def _to_nm(image) -> float:
    return 1e9 if (image.unit or "").strip().lower() in ("m", "meter", "meters", "metre", "metres") else 1.0


def _add(arrays: dict, name: str, image, scale_m: bool = False) -> None:
    data = _data(image)
    if data is not None:
        arrays[name] = data * (_to_nm(image) if scale_m else 1.0)


def _time_arrays(arrays: dict, time) -> None:
    if time is None:
        return
    if time.frame_numbers:
        arrays["frame_counter"] = np.asarray(time.frame_numbers, dtype=np.int64)
    if time.timestamps:
        t = np.asarray(time.timestamps, dtype=float)
        arrays["frame_time_s"] = t - t[0]


@blas.on_one_thread  # the same modes on every machine
def _derived(arrays: dict) -> None:
    """R s and M^-1 c from what the standard holds, when the file does not give them."""
    if "measured_modes" not in arrays and "slopes" in arrays and "reconstructor" in arrays:
        if arrays["reconstructor"].shape[1] == arrays["slopes"].shape[1]:
            arrays["measured_modes"] = arrays["slopes"] @ arrays["reconstructor"].T
    if "command_modes" not in arrays and "commands" in arrays and "modes_to_commands" in arrays:
        m = arrays["modes_to_commands"]
        if m.shape[0] == arrays["commands"].shape[1]:
            arrays["command_modes"] = arrays["commands"] @ np.linalg.pinv(m).T
