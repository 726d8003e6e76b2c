"""LBT tracking-number (TN) folders: the layout of LBT's AO telemetry as LBTO's elab_lib reads it.

A TN (``YYYYMMDD_hhmmss``) is the folder ``<ADOPT_MEAS>/adsec_data/<YYYYMMDD>/Data_<TN>/``
(elab_lib aoelab__define.pro:15-16).  soulctl reads and writes the folder itself; the layout,
and where each assumption comes from (LBTO/elab_lib, docs/telemetry-formats.md has the table):

* ``FramesCounter_<TN>.fits``: one frame number per recorded frame (aoelab:195,
  aoframes_counter__define.pro:16-18).  Decimation = median(diff) - 1 and a step larger than
  decimation + 1 is a gap (aoframes_counter:51-56).  soulctl keeps every row with its frame
  number (field frame_counter): gaps are flagged, never filled, and never misalign the rows;
  analyses that need every frame refuse decimated or gapped records.
* ``Slopes_<TN>.fits``, ``Modes_<TN>.fits``, ``Commands_<TN>.fits``, ``Positions_<TN>.fits``:
  astropy shape (frames, n) - IDL reads them and transposes to [niter, n]
  (aotime_series__define.pro:3-5, aoslopes:55-57).  Slopes are interleaved x, y, x, y
  (aoslopes:113-114); soulctl's are [sx..., sy...].  Modes are the integrated modal commands
  (aomodes:34), i.e. soulctl's command_modes; Commands are actuator commands; Positions the
  mirror's measured positions.  Modes, Commands and Positions are metres of mirror surface:
  elab_lib multiplies them by 1e9 x reflcoef to get nm of wavefront, reflcoef = 2 on sky
  (aocommands:24, aomodes:26, aoelab:159).
* ``wfs.fits``: a header of WFS keywords; the loop rate is ``ocam2.FRAMERATE`` (SOUL) or
  ``ccd39.FRAMERATE`` (FLAO) (aoocam2k__define.pro:14-31, aoccd39__define.pro:13-18), the
  modulation ``tt.LAMBDA_D`` (aowfs_status__define.pro:30).  Written and read as HIERARCH
  cards (the keyword names are longer than 8 characters; no real header was seen).
* Gains: LBT keeps them in ``adsec.sav`` (variable g_gain, an IDL save file, read here with
  scipy.io.readsav) or a calibration-tree FITS file it names (aocontrol__define.pro:151-168).
  soulctl reads adsec.sav's g_gain when present, else ``Gains_<TN>.fits`` in the folder, the
  file soulctl writes (a soulctl convention: it cannot write IDL save files).
* The reconstructor ``Rec_*.fits`` lives in the calibration tree (aoelab:218), astropy shape
  (modes, slopes) (aorecmatrix:42); soulctl writes ``Rec_<TN>.fits`` in the folder (columns in
  LBT's interleaved slope order, m of surface per slope unit) and reads any ``Rec_*.fits``
  there; R s is then its product with the slopes.
* The loop delay is not in the folder (elab_lib computes it from the camera's timing,
  aodelay__define.pro): soulctl writes keyword SOULDLY (frames) in wfs.fits and reads it when
  present.  soulctl's other records (R s, residual and disturbance modes, k, flux, the gain
  history, auxiliary records, configuration) go to ``soulctl_<TN>.fits`` (HDUs tagged by
  keyword SOULNAME, as in the AOT files), which LBT's tools ignore.
"""

from __future__ import annotations

import datetime
import json
import os
import re
import shutil
import tempfile
from pathlib import Path

import numpy as np
from astropy.io import fits

from ..errors import InputError
from ..files import check_output_path
from .aot import EXTRA_KEY, tagged_hdu
from .schema import REQUIRED, TelemetryReader, check_slope_pairs, nested

NM_PER_M_SURFACE = 2e9  # 1e9 x reflcoef, reflcoef = 2 on sky (aoelab:159)
RATE_KEYWORDS = ("ocam2.FRAMERATE", "ccd39.FRAMERATE")
MODULATION_KEYWORD = "tt.LAMBDA_D"
DELAY_KEYWORD = "SOULDLY"
SERIES = {  # file stem -> (soulctl field, scale from the file's unit to soulctl's)
    "Modes": ("command_modes", NM_PER_M_SURFACE),
    "Commands": ("commands", NM_PER_M_SURFACE),
}
TN_PATTERN = re.compile(r"^FramesCounter_(\d{8}_\d{6})\.fits$")


def deinterleaved(a: np.ndarray) -> np.ndarray:
    """Columns x, y, x, y (LBT, aoslopes:113-114) -> [x..., y...] (soulctl)."""
    return np.concatenate([a[:, 0::2], a[:, 1::2]], axis=1)


def interleaved(a: np.ndarray) -> np.ndarray:
    """Columns [x..., y...] (soulctl) -> x, y, x, y (LBT)."""
    out = np.empty_like(a)
    half = a.shape[1] // 2
    out[:, 0::2], out[:, 1::2] = a[:, :half], a[:, half:]
    return out


def tracking_number(folder: Path) -> str:
    """The TN of a folder: from its FramesCounter_<TN>.fits (InputError if none or several)."""
    found = sorted(m.group(1) for name in os.listdir(folder) if (m := TN_PATTERN.match(name)))
    if len(found) != 1:
        what = "no FramesCounter_<TN>.fits" if not found else f"several tracking numbers ({', '.join(found[:3])})"
        raise InputError(f"telemetry folder {folder} holds {what}: an LBT tracking-number folder holds one FramesCounter_<TN>.fits")
    return found[0]


def _read_fits(path: Path, what: str) -> tuple[np.ndarray | None, fits.Header]:
    try:
        with fits.open(path, memmap=False) as hdus:
            data = hdus[0].data
            return (None if data is None else np.asarray(data)), hdus[0].header
    except (OSError, ValueError, TypeError) as e:
        raise InputError(f"telemetry folder: {path.name} is not a readable FITS file ({' '.join(str(e).split())[:160]})") from None


def _series(folder: Path, stem: str, tn: str, frames: int) -> np.ndarray | None:
    path = folder / f"{stem}_{tn}.fits"
    if not path.exists():
        return None
    data, _ = _read_fits(path, stem)
    if data is None or data.ndim != 2:
        raise InputError(
            f"telemetry folder {folder}: {path.name} must hold a (frames, n) image, got {None if data is None else data.shape}"
        )
    if data.shape[0] != frames:
        raise InputError(
            f"telemetry folder {folder}: {path.name} has {data.shape[0]} frames, FramesCounter_{tn}.fits has {frames}: they must agree"
        )
    return data.astype(np.float64)


def _header_value(header: fits.Header, keys, folder: Path) -> float | None:
    for key in keys:
        for k in (key, f"HIERARCH {key}"):
            if k in header:
                value = header[k]
                if isinstance(value, bool) or not isinstance(value, (int, float)):
                    raise InputError(f"telemetry folder {folder}: wfs.fits keyword {key} must be a number, got {str(value)[:40]!r}")
                return float(value)
    return None


def read_lbt(path: str | Path, required: tuple[str, ...] = REQUIRED) -> TelemetryReader:
    """An LBT TN folder as soulctl's model (see the module); InputError naming the file."""
    folder = Path(path)
    if not folder.is_dir():
        raise InputError(f"telemetry folder {path} is not a folder")
    tn = tracking_number(folder)
    counter, _ = _read_fits(folder / f"FramesCounter_{tn}.fits", "FramesCounter")
    if counter is None or counter.ndim != 1 or counter.size < 1 or counter.dtype.kind not in "iuf":
        raise InputError(f"telemetry folder {folder}: FramesCounter_{tn}.fits must hold a 1-D frame counter (numbers) of at least 1 frame")
    if not np.all(np.isfinite(counter) & (counter == np.floor(counter)) & (np.abs(counter) < 2**62)):
        raise InputError(f"telemetry folder {folder}: FramesCounter_{tn}.fits must hold whole frame numbers (no NaN)")
    frames = counter.size
    arrays: dict = {"frame_counter": counter.astype(np.int64) - int(counter[0])}
    attributes: dict = {}
    slopes = _series(folder, "Slopes", tn, frames)
    if slopes is not None and slopes.shape[1] % 2:
        raise InputError(f"telemetry folder {folder}: Slopes_{tn}.fits has {slopes.shape[1]} columns, expected x, y pairs")
    if slopes is not None:
        arrays["slopes"] = deinterleaved(slopes)
    for stem, (name, scale) in SERIES.items():
        data = _series(folder, stem, tn, frames)
        if data is not None:
            arrays[name] = data * scale
    _wfs_header(folder, attributes)
    if "rate_hz" in attributes:
        arrays["frame_time_s"] = arrays["frame_counter"] / attributes["rate_hz"]
    _gains(folder, tn, arrays)
    _reconstructor(folder, arrays)
    _extras(folder / f"soulctl_{tn}.fits", arrays, attributes)
    if "gains" in arrays:
        attributes.setdefault("n_modes", len(arrays["gains"]))
    return TelemetryReader.from_arrays(path, arrays, attributes, required)


def _wfs_header(folder: Path, attributes: dict) -> None:
    path = folder / "wfs.fits"
    if not path.exists():
        return
    _, header = _read_fits(path, "wfs")
    rate = _header_value(header, RATE_KEYWORDS, folder)
    if rate is not None:
        attributes["rate_hz"] = rate
    delay = _header_value(header, (DELAY_KEYWORD,), folder)
    if delay is not None:
        attributes["delay_frames"] = delay


def _gains(folder: Path, tn: str, arrays: dict) -> None:
    sav = folder / "adsec.sav"
    if sav.exists():
        from scipy.io import readsav

        try:
            g = readsav(str(sav)).get("g_gain")
        except Exception as e:  # noqa: BLE001 - scipy raises several kinds for a bad save file
            raise InputError(f"telemetry folder {folder}: adsec.sav is not a readable IDL save file ({e})") from None
        if g is not None:
            arrays["gains"] = np.asarray(g, dtype=float).ravel()
            return
    path = folder / f"Gains_{tn}.fits"
    if path.exists():
        data, _ = _read_fits(path, "Gains")
        if data is not None:
            arrays["gains"] = np.asarray(data, dtype=float).ravel()


def _reconstructor(folder: Path, arrays: dict) -> None:
    recs = sorted(folder.glob("Rec_*.fits"))
    if not recs:
        return
    r, _ = _read_fits(recs[0], "Rec")
    if r is None or r.ndim != 2:
        return
    r = deinterleaved(r) * NM_PER_M_SURFACE  # columns in soulctl's slope order, nm
    arrays["reconstructor"] = r
    if "slopes" in arrays and r.shape[1] == arrays["slopes"].shape[1]:
        arrays["measured_modes"] = arrays["slopes"] @ r.T


def _extras(path: Path, arrays: dict, attributes: dict) -> None:
    """soulctl's own records of a folder it wrote (InputError naming the file if damaged)."""
    if not path.exists():
        return
    try:
        with fits.open(path, memmap=False) as hdus:
            tagged = [(h.header[EXTRA_KEY], h.data) for h in hdus if EXTRA_KEY in h.header]
        for name, data in tagged:
            if data is None:
                raise ValueError(f"HDU {name} holds no data")
            data = np.asarray(data)
            if name in ("configuration", "run_description", "status", "partial_reason", "soulctl_version"):
                attributes[name] = bytes(data.astype(np.uint8)).decode("utf-8")
            elif name in ("schema_version", "telemetry_every", "diverged_at", "n_modes"):
                attributes[name] = int(data.ravel()[0])
            else:
                arrays[name] = data
    except (OSError, ValueError, TypeError, IndexError, UnicodeDecodeError) as e:
        first = " ".join(str(e).split()).split(". ")[0][:160]
        raise InputError(f"telemetry folder {path.parent}: {path.name} is not a readable soulctl record ({first})") from None


# ----------------------------------------------------------------------------------------- writing


def write_lbt(path: str | Path, arrays: dict, attributes: dict, configuration: dict) -> None:
    """A record as an LBT TN folder (a new folder, created whole under a temporary name and
    renamed; an existing folder is refused).  The TN is the folder's name when it ends in a
    TN (e.g. Data_20261126_120000), else today's date and time."""
    folder = Path(str(path).rstrip("/"))
    check_slope_pairs(arrays, "an LBT folder (interleaved x, y slopes)")
    if folder.exists():
        raise InputError(f"telemetry folder {folder} exists: soulctl writes a tracking-number folder only as a new folder")
    check_output_path(folder, "telemetry folder")
    m = re.search(r"(\d{8}_\d{6})$", folder.name)
    tn = m.group(1) if m else datetime.datetime.now(datetime.UTC).strftime("%Y%m%d_%H%M%S")
    tmp = Path(tempfile.mkdtemp(prefix=".soulctl-", dir=folder.parent if str(folder.parent) else "."))
    try:
        _write_files(tmp, tn, arrays, attributes, configuration)
        os.replace(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _write_files(folder: Path, tn: str, arrays: dict, attributes: dict, configuration: dict) -> None:
    counter = np.asarray(arrays.get("frame_counter", np.arange(_frames(arrays))), dtype=np.int64)
    counter = counter.astype(np.int32) if counter.size and counter.max() < 2**31 else counter  # elab_lib's lonarr where it fits
    fits.PrimaryHDU(counter).writeto(folder / f"FramesCounter_{tn}.fits")
    if "slopes" in arrays:
        fits.PrimaryHDU(interleaved(np.asarray(arrays["slopes"], dtype=np.float32))).writeto(folder / f"Slopes_{tn}.fits")
    for stem, (name, scale) in SERIES.items():
        if name in arrays:
            fits.PrimaryHDU((np.asarray(arrays[name]) / scale).astype(np.float32)).writeto(folder / f"{stem}_{tn}.fits")
    if "mirror_modes" in arrays and "modes_to_commands" in arrays:
        positions = np.asarray(arrays["mirror_modes"]) @ np.asarray(arrays["modes_to_commands"]).T / NM_PER_M_SURFACE
        fits.PrimaryHDU(positions.astype(np.float32)).writeto(folder / f"Positions_{tn}.fits")
    header = fits.Header()
    if "rate_hz" in attributes:
        header[f"HIERARCH {RATE_KEYWORDS[0]}"] = float(attributes["rate_hz"])
    if "delay_frames" in attributes:
        header[DELAY_KEYWORD] = (float(attributes["delay_frames"]), "loop delay [frames] (soulctl)")
    modulation = nested(configuration, "observation", "wfs", "modulation_lambda_over_d", number=True)
    if modulation is not None:
        header[f"HIERARCH {MODULATION_KEYWORD}"] = float(modulation)
    fits.PrimaryHDU(header=header).writeto(folder / "wfs.fits")
    if "gains" in arrays:
        fits.PrimaryHDU(np.asarray(arrays["gains"], dtype=np.float32)).writeto(folder / f"Gains_{tn}.fits")
    if "reconstructor" in arrays:
        r = interleaved(np.asarray(arrays["reconstructor"]) / NM_PER_M_SURFACE)
        fits.PrimaryHDU(r.astype(np.float32)).writeto(folder / f"Rec_{tn}.fits")
    _write_extras(folder / f"soulctl_{tn}.fits", arrays, attributes, configuration)


def _frames(arrays: dict) -> int:
    return next((len(v) for k, v in arrays.items() if k in ("measured_modes", "command_modes", "slopes", "commands")), 0)


LBT_HELD = ("frame_counter", "frame_time_s", "slopes", "command_modes", "commands", "gains", "reconstructor")


def _write_extras(path: Path, arrays: dict, attributes: dict, configuration: dict) -> None:
    hdus = fits.HDUList([fits.PrimaryHDU()])
    for name, data in arrays.items():
        if name not in LBT_HELD or name in ("command_modes", "commands", "gains", "reconstructor"):  # exact copies (LBT's are float32)
            hdus.append(tagged_hdu(name, np.asarray(data)))
    texts = {"configuration": json.dumps(configuration)} | {
        k: str(attributes[k]) for k in ("run_description", "status", "partial_reason", "soulctl_version") if k in attributes
    }
    for name, text in texts.items():
        hdus.append(tagged_hdu(name, np.frombuffer(text.encode("utf-8"), dtype=np.uint8)))
    for name in ("schema_version", "telemetry_every", "diverged_at", "n_modes"):
        if name in attributes:
            hdus.append(tagged_hdu(name, np.array([int(attributes[name])], dtype=np.int64)))
    hdus.writeto(path)
