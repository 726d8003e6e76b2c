"""LBT tracking-number (TN) folders, as LBT's supervisor writes them and LBTO's elab_lib reads them.

A TN (``YYYYMMDD_hhmmss``, local time) is the folder ``<...>/adsec_data/<YYYYMMDD>/Data_<TN>/``
(icprog/MagAO lib/Paths.cpp:27-41; elab_lib aoelab__define.pro:15-16).  The writer is the
supervisor shared by FLAO, LBTI and MagAO (public as icprog/MagAO): OptLoopDiagnostic writes one
primary HDU per file (lib/iolib.c:430-495), the per-frame vectors along NAXIS1
(OptLoopDiagnostic.cpp:776-971), i.e. astropy shape (frames, n):

* ``FramesCounter_<TN>.fits``: the WFS frame number of each row, 32-bit integers (861-867).
  Decimation = median(diff) - 1; a larger step is a gap (aoframes_counter__define.pro:47-57).
  soulctl keeps every row with its frame number: gaps are flagged, never filled.
* ``Slopes_<TN>.fits`` (frames, 1600): interleaved x, y (makePupils.py:258-265), padded to 1600
  whatever the pupils (340-341); the valid ones are the reconstructor's columns.
* ``Modes_<TN>.fits``, ``Commands_<TN>.fits``, ``Positions_<TN>.fits`` (frames, 672): the
  integrated modal commands, the actuator commands and positions, m of mirror surface; 672 is
  the adaptive secondary's width whatever the modes controlled (AdSecConstants.h:50-62).
* ``wfs.fits``: a header of HIERARCH cards (``Keywords``): the rate as the camera's FRAMERATE,
  ``ocam2`` (SOUL) or ``ccd39`` (FLAO), often as text, '-9999' when unknown.
* ``adsec.sav``: an IDL save file, the gains ``g_gain`` (672) and the calibration files' names
  (``AdsecSav``).  The reconstructor ``Rec_*.fits`` (672, 1600), zero-padded, lives in the
  calibration tree; soulctl reads one copied into the folder, prefers the one adsec.sav names,
  and trims the padding as elab_lib does (``_layout``), its header's IIR filters included
  (``IirHeader``).

What the record cannot give is absent from the model, with a ``Note`` saying why (`telemetry
inspect` prints them): a rate of '-9999', a delay that elab_lib's computeDelay cannot derive, a
reconstructor left in the calibration tree.  docs/telemetry-formats.md has the table of every
assumption with its source.  soulctl's other records (R s, residual and disturbance modes, k,
flux, the gain history, auxiliary records, configuration) go to ``soulctl_<TN>.fits`` (HDUs
tagged by keyword SOULNAME, as in the AOT files), which LBT's tools ignore.
"""

from __future__ import annotations

import datetime
import json
import math
import os
import re
import shutil
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from astropy.io import fits

from ..control.delay import DelayModel
from ..control.filters import unit_coefficients
from ..disturbance.modal_psd import radial_order
from ..errors import InputError
from ..files import check_output_path, input_file
from ..ranges import DELAY_FRAMES, RECORD_RATE_HZ
from .aot import EXTRA_KEY, tagged_hdu
from .schema import LBT_SYSTEM, REQUIRED, Note, TelemetryReader, check_slope_pairs, nested

SAV_MAX_BYTES = 256 * 2**20  # adsec.sav: gains, names and a few structures (the accelerometers' data among them)
NM_PER_M = 1e9
# elab_lib's conversions to nm of wavefront (docs/telemetry-formats.md): Modes, Commands and
# Positions are m of mirror surface, x 1e9 x reflcoef, reflcoef 4 in retro-reflection and 2
# otherwise (aomodes__define.pro:31, aoelab__define.pro:166); R s is x 1e9 x reflcoef x the
# calibration's mismatch (2 unless in retro-reflection, the interaction matrices being measured
# double-pass), i.e. 4e9 in every mode (aoresidual_modes__define.pro:40-44).
RECONSTRUCTOR_NM_PER_M = 4e9
INVALID = ("-9999", "UNKNOWN", "")  # the supervisor's unknown values (icprog/MagAO WfsArbScripts.py:440-441)
SOUL, FLAO = "ocam2", "ccd39"  # the WFS cameras: SOUL's OCAM2K, FLAO's CCD39 (aowfs_status__define.pro:55-59)
MODULATION_KEYWORD = "tt.LAMBDA_D"
DELAY_KEYWORD = "SOULDLY"
LBT_MODAL_ROWS = 672  # the adaptive secondary's modal and actuator vectors (OptLoopDiagnostic.cpp:845-883)
SERIES = {"Modes": "command_modes", "Commands": "commands"}  # file stem -> field (m of surface -> nm, x reflcoef)
TN_PATTERN = re.compile(r"^FramesCounter_(\d{8}_\d{6})\.fits$")
# elab_lib's loop delay, computeDelay: 1/f + t_readout + t_computation + t_ASM / 2 (seconds)
SOUL_READOUT_S = (0.48e-3, 0.24e-3, 0.24e-3, 0.20e-3, 0.16e-3)  # by ocam2.MODE 1..5 (aoocam2k__define.pro:58-59)
FLAO_READOUT_S = ((600.0, (0.95e-3, 0.81e-3, 0.89e-3, 0.68e-3)), (423.0, (0.95e-3, 1.56e-3, 0.89e-3, 0.68e-3)))  # above f, by binning
FLAO_READOUT_SLOW_S = (2.3e-3, 1.56e-3, 0.89e-3, 0.68e-3)  # f <= 423 Hz (aoccd39__define.pro:43-45)
COMPUTATION_S = {SOUL: 0.66e-3, FLAO: 0.72e-3}  # aoocam2k:53, aoccd39:39
ASM_SET_S = 1e-3  # counted at half (aoocam2k:57, 62)


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


def _read_fits(path: Path) -> tuple[np.ndarray | None, fits.Header]:
    """The primary HDU of a member of the folder (a regular file; InputError naming it)."""
    input_file(path, f"telemetry folder: {path.name}")
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
    data, _ = _read_fits(path)
    if data is None or data.ndim != 2:
        raise InputError(
            f"telemetry folder {folder}: {path.name} must hold a (frames, n) image, got {None if data is None else data.shape}"
        )
    if data.shape[0] != frames:
        raise InputError(
            f"telemetry folder {folder}: {path.name} has {data.shape[0]} frames, FramesCounter_{tn}.fits has {frames}: they must agree"
        )
    return data.astype(np.float64)


class Keywords:
    """A header's keywords as LBT's supervisor writes them and elab_lib reads them: every key of
    wfs.fits a HIERARCH card (icprog/MagAO PyModules/AdOpt/fits_lib.py:46-47), numbers often
    as text ('%5.2f', WfsArbScripts.py:480), '-9999' or 'UNKNOWN' where the supervisor did not
    know the value (440-441); elab_lib matches the key with or without 'HIERARCH ', in any
    case, strips the quotes and converts (aoget_fits_keyword.pro)."""

    def __init__(self, header: fits.Header, where: str):
        self.where = where
        self.cards: dict[str, object] = {}
        for card in header.cards:
            key = str(card.keyword).upper()
            self.cards.setdefault(key[9:] if key.startswith("HIERARCH ") else key, card.value)

    def raw(self, key: str):
        value = self.cards.get(key.upper())
        return None if value is None or isinstance(value, fits.card.Undefined) else value

    def text(self, key: str) -> str | None:
        """The value as text, None when absent or unknown to the writer."""
        value = self.raw(key)
        text = None if value is None else str(value).strip().strip("'").strip()
        return None if text is None or text in INVALID else text

    def number(self, key: str) -> float | None:
        """The value as a number (a number or its text), None when absent or unknown to the
        writer ('-9999'); InputError for other text."""
        value = self.raw(key)
        if value is None:
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise InputError(f"{self.where}: keyword {key} must be a number, got {str(value)[:40]!r}")
        text = str(value).strip().strip("'").strip()
        if text in INVALID:
            return None
        try:
            x = float(text)
        except ValueError:
            raise InputError(f"{self.where}: keyword {key} must be a number (or a number as text), got {text[:40]!r}") from None
        if not math.isfinite(x):
            raise InputError(f"{self.where}: keyword {key} must be a finite number, got {text[:40]!r}")
        return None if x == -9999 else x

    def elab_number(self, key: str) -> float:
        """The number IDL's float() makes of it in elab_lib: 0 when absent, -9999 when unknown."""
        x = self.number(key)
        return x if x is not None else (0.0 if self.raw(key) is None else -9999.0)

    def missing(self, key: str) -> str:
        """Why ``number`` or ``text`` gave None, in words."""
        value = self.raw(key)
        return f"{self.where} has no {key}" if value is None else f"{self.where}: {key} is {str(value).strip()!r}, unknown to its writer"

    @property
    def camera(self) -> str:
        """SOUL's OCAM2K when ocam2.MODE is there, else FLAO's CCD39 (elab_lib's isSoul,
        aowfs_status__define.pro:125-127)."""
        return SOUL if self.raw("ocam2.MODE") is not None else FLAO


def operation_mode(wfs: Keywords | None, tn: str) -> str:
    """elab_lib's operation mode of a TN (aoelab__define.pro:119-160): ONSKY when the telescope
    tracks, else RR (retro-reflector) or ARGOScal by the unit, the calibration cube's stage and
    the lamp; RR without wfs.fits (the solar tower)."""
    if wfs is None:
        return "RR"
    if wfs.elab_number("tel.TEL.ISTRACKING") != 0:
        return "ONSKY"
    unit = wfs.text("W_UNIT") or ""
    cube, lamp = wfs.elab_number("cubestage.POSITION"), wfs.elab_number("lamp.INTENSITY")
    if unit.startswith("LBTI") and unit[4:6] in ("DX", "SX"):
        return "RR" if -100 < cube <= -60 else "ARGOScal"
    if unit.startswith("MAG"):
        return "RR" if lamp > 0.001 else "ARGOScal"
    after = tn >= "20200130_120000"  # julday >= 2458879
    if (cube > -40) if after else (cube < -40):
        return "ARGOScal"
    return "RR" if lamp > 0.001 else "ARGOScal"


def elab_lib_delay_s(camera: str, rate_hz: float, mode: int | None = None, binning: int | None = None) -> float:
    """LBT's loop delay as elab_lib computes it (computeDelay: aoocam2k__define.pro:49-64 for
    SOUL's camera by its readout mode, aoccd39__define.pro:34-51 for FLAO's by its binning and
    rate): 1/f + t_readout + t_computation + t_ASM / 2, seconds."""
    if camera == SOUL:
        if mode is None or mode not in range(1, len(SOUL_READOUT_S) + 1):
            raise InputError(f"ocam2.MODE must be 1..{len(SOUL_READOUT_S)}, got {mode}")
        readout = SOUL_READOUT_S[mode - 1]
    else:
        if binning is None or binning not in range(1, 5):
            raise InputError(f"ccd39.BINNING must be 1..4, got {binning}")
        table = next((t for above, t in FLAO_READOUT_S if rate_hz > above), FLAO_READOUT_SLOW_S)
        readout = table[binning - 1]
    return 1.0 / rate_hz + readout + COMPUTATION_S[camera] + 0.5 * ASM_SET_S


def _wfs_keywords(folder: Path, notes: list[Note]) -> Keywords | None:
    path = folder / "wfs.fits"
    if not path.exists():
        notes.append(Note("", "no wfs.fits: the rate, the camera and the operation mode are unknown"))
        return None
    return Keywords(_read_fits(path)[1], f"telemetry folder {folder}: wfs.fits")


def _rate(wfs: Keywords | None, folder: Path, tn: str, counter: np.ndarray, notes: list[Note]) -> float | None:
    """The camera's FRAMERATE keyword (aoocam2k__define.pro:14, aoccd39__define.pro:13), else
    the rate of SystemTimestamp_<TN>.fits (seconds, aotimestamps__define.pro:22), else None."""
    rate, why = None, "no wfs.fits"
    if wfs is not None:  # the camera's; the other's where a header holds only that (elab_lib would read 0 Hz)
        keys = [f"{c}.FRAMERATE" for c in (wfs.camera, SOUL, FLAO)]
        key = next((k for k in keys if wfs.raw(k) is not None), keys[0])
        rate, why = wfs.number(key), wfs.missing(key)
        if rate is not None:
            return RECORD_RATE_HZ.check(rate, f"telemetry folder {folder}: wfs.fits keyword {key}")
    stamps = folder / f"SystemTimestamp_{tn}.fits"
    if stamps.exists() and counter.size > 2:
        t, _ = _read_fits(stamps)
        if t is not None and t.ndim == 1 and t.size == counter.size and np.all(np.isfinite(t)) and np.all(np.diff(t) > 0):
            rate = float((counter[-1] - counter[0]) / (t[-1] - t[0]))  # over the record: time stamps of 1e9 s hold 0.2 us
            if RECORD_RATE_HZ.contains(rate):
                notes.append(Note("rate_hz", f"rate {rate:.6g} Hz from {stamps.name} ({why})"))
                return rate
    notes.append(Note("rate_hz", why))
    return None


def _delay(wfs: Keywords | None, rate: float | None, notes: list[Note]) -> float | None:
    """SOULDLY (frames, soulctl's own keyword), else elab_lib's computeDelay for the camera."""
    if wfs is None:
        return None
    recorded = wfs.number(DELAY_KEYWORD)
    if recorded is not None:
        return DELAY_FRAMES.check(recorded, f"{wfs.where} keyword {DELAY_KEYWORD}")
    unit = wfs.text("W_UNIT") or ""
    key = "ocam2.MODE" if wfs.camera == SOUL else "ccd39.BINNING"
    setting = wfs.number(key)
    if rate is None or setting is None or unit.startswith("MAG"):
        why = "MagAO's timing is not LBT's" if unit.startswith("MAG") else ("the rate is unknown" if rate is None else wfs.missing(key))
        notes.append(Note("delay_frames", f"no delay: elab_lib's computeDelay needs the rate and {key} ({why})"))
        return None
    try:
        kind = {"mode" if wfs.camera == SOUL else "binning": int(setting)}
        seconds = elab_lib_delay_s(wfs.camera, rate, **kind)
    except InputError as e:
        notes.append(Note("delay_frames", f"no delay: {e}"))
        return None
    frames = seconds * rate
    source = "aoocam2k__define.pro:49-64" if wfs.camera == SOUL else "aoccd39__define.pro:34-51"
    text = f"delay {frames:.3f} frames ({seconds * 1e3:.3f} ms) from elab_lib's computeDelay"
    notes.append(Note("delay_frames", f"{text} ({source}, {key} {int(setting)})"))
    return frames


class AdsecSav:
    """adsec.sav, the IDL save file LBT's supervisor writes (fsm_savestatus.pro:5-21): the gain
    vector g_gain (672 per mode) and, in structure status, the names of the calibration files
    (b0_a: the reconstructor, aoadsec_status__define.pro:16-44)."""

    def __init__(self, folder: Path, notes: list[Note]):
        self.gains: np.ndarray | None = None
        self.reconstructor_name: str | None = None
        path = folder / "adsec.sav"
        if not path.exists():
            return
        input_file(path, "telemetry folder: adsec.sav", max_bytes=SAV_MAX_BYTES)
        from scipy.io import readsav

        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                content = readsav(str(path))
        except Exception as e:  # noqa: BLE001 - scipy raises several kinds for a bad save file
            notes.append(Note("gains", f"adsec.sav is not a readable IDL save file ({' '.join(str(e).split())[:120]})"))
            return
        g = content.get("g_gain")
        if g is not None:
            g = np.asarray(g)
            if g.dtype.kind not in "iuf" or g.ndim > 2 or not np.all(np.isfinite(g)):
                raise InputError(f"telemetry folder {folder}: adsec.sav's g_gain must be a vector of finite numbers")
            self.gains = g.astype(float).ravel()
        self.reconstructor_name = _struct_text(content.get("status"), "b0_a")


def _struct_text(struct, tag: str) -> str | None:
    try:
        value = struct[tag][0] if struct is not None else None
    except (KeyError, ValueError, IndexError, TypeError):
        return None
    if isinstance(value, bytes):
        value = value.decode("latin1")
    return Path(value.strip()).name if isinstance(value, str) and value.strip() else None


def _reconstructor_file(folder: Path, sav: AdsecSav, notes: list[Note]) -> Path | None:
    """The folder's Rec_*.fits: the one adsec.sav names when it is there, else the first."""
    recs = sorted(folder.glob("Rec_*.fits"))
    named = [p for p in recs if p.name == sav.reconstructor_name]
    if named or recs:
        return (named or recs)[0]
    where = f"adsec.sav names {sav.reconstructor_name}" if sav.reconstructor_name else "its name is in adsec.sav's status.b0_a"
    notes.append(
        Note("reconstructor", f"no Rec_*.fits in the folder ({where}; elab_lib reads it from the calibration tree): copy it here for R s")
    )
    return None


def _reconstructor(folder: Path, sav: AdsecSav, notes: list[Note]) -> tuple[np.ndarray | None, Keywords | None]:
    """The reconstructor (astropy shape (modes, slopes)) and its header's keywords, or Nones."""
    path = _reconstructor_file(folder, sav, notes)
    if path is None:
        return None, None
    rec, header = _read_fits(path)
    if rec is None or rec.ndim != 2 or rec.dtype.kind not in "iuf" or not np.all(np.isfinite(rec)):
        raise InputError(f"telemetry folder {folder}: {path.name} must hold a (modes, slopes) matrix of finite numbers")
    return rec, Keywords(header, f"telemetry folder {folder}: {path.name}")


@dataclass(frozen=True)
class IirHeader:
    """The IIR filters of a SOUL reconstructor's header (hdr_rec_to_iir_params.pro:21-38): the
    modes with an IIR (MODEIDX<k>) and its coefficients IIRNUM<i><j> / IIRDEN<i><j> (i the
    power of z, j the filter: elab_int_iir.pro:19-24's order, ascending powers of z), the
    other modes' forgetting factors (FF_NOEXM, FF_MINVA, FF_EXP: aocontrol__define.pro:326-339),
    and the modal rows that are modes, nmodes_filter: the rest of the 672 carry the IIRs' states."""

    modes: tuple[int, ...]  # 0-based
    num: np.ndarray  # (coefficients, filters)
    den: np.ndarray
    ff_plain: int
    ff_min: float
    ff_exp: float

    @property
    def n_modes_filter(self) -> int:
        return LBT_MODAL_ROWS - 2 * len(self.modes) * (self.num.shape[0] - 1) + len(self.modes)

    @classmethod
    def of(cls, keys: Keywords) -> IirHeader | None:
        n_iir = keys.number("MODEIDXN")
        if n_iir is None:
            return None
        sizes = [keys.number(k) for k in ("IIRNELE0", "IIRNELE1")]
        if not all(x is not None and 1 <= x <= 10 and x == int(x) for x in [*sizes, n_iir]):
            raise InputError(f"{keys.where}: MODEIDXN, IIRNELE0 and IIRNELE1 must be integers in 1..10 (elab_lib reads single digits)")
        n_coef, n_filters = (int(x) for x in sizes)  # type: ignore[arg-type]
        num, den = (
            np.array([[keys.elab_number(f"IIR{w}{i}{j}") for j in range(n_filters)] for i in range(n_coef)]) for w in ("NUM", "DEN")
        )
        modes = tuple(int(keys.elab_number(f"MODEIDX{k}")) for k in range(int(n_iir)))
        plain = keys.number("FF_NOEXM")
        return cls(modes, num, den, int(plain or 0), keys.elab_number("FF_MINVA"), keys.elab_number("FF_EXP"))

    def controller(self, n_modes: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(num, den) per mode in powers of z^-1 as the header states them (the reader takes
        their scale into the gains, ``unit_coefficients``), or None when the header's filters do
        not map onto its modes (one filter for all, or one per mode)."""
        if self.num.shape[1] not in (1, len(self.modes)) or max(self.modes) >= n_modes or min(self.modes) < 0:
            return None
        width = max(self.num.shape[0], 2)
        num, den = np.zeros((n_modes, width)), np.zeros((n_modes, width))
        ff = self.forgetting(n_modes)
        num[:, 0], den[:, 0], den[:, 1] = 1.0, 1.0, -ff
        for k, mode in enumerate(self.modes):
            j = k if self.num.shape[1] > 1 else 0
            b, a = self.num[::-1, j], self.den[::-1, j]  # ascending powers of z -> powers of z^-1
            num[mode], den[mode] = 0.0, 0.0
            num[mode, : len(b)], den[mode, : len(a)] = b, a
        return num, den

    def forgetting(self, n_modes: int) -> np.ndarray:
        """The integrator modes' forgetting factors (aocontrol__define.pro:326-339): 1 for the
        first FF_NOEXM, then 1 - (1 - FF_MINVA) ((n - n0) / (n_max - n0))^FF_EXP by radial order n."""
        plain = [m for m in range(n_modes) if m not in self.modes]
        order = radial_order(np.arange(1, len(plain) + 1))
        n0 = order[min(self.ff_plain, len(order) - 1)] if len(order) else 0.0
        span = max(float(order.max() - n0), 1.0) if len(order) else 1.0
        ratio = np.clip((order - n0) / span, 0.0, None)
        ff = np.minimum(1.0, 1.0 - (1.0 - self.ff_min) * ratio**self.ff_exp)
        ff[: self.ff_plain] = 1.0
        out = np.ones(n_modes)
        out[plain] = ff
        return out


@dataclass
class Layout:
    """What of the writer's padded columns the record really holds: its modes (Modes_, the
    gains, the reconstructor's rows) and its slopes (Slopes_, the reconstructor's columns)."""

    n_modes: int | None
    n_slopes: int | None
    iir: IirHeader | None = None


def _last_varying(data: np.ndarray | None) -> int | None:
    """1 + the last column of ``data`` that is not constant over the record (None without data)."""
    if data is None:
        return None
    varying = np.flatnonzero(np.ptp(data, axis=0) > 0) if len(data) > 1 else np.flatnonzero(np.any(data != 0, axis=0))
    return int(varying[-1]) + 1 if len(varying) else data.shape[1]


def _layout(rec: np.ndarray | None, rec_keys: Keywords | None, modes: np.ndarray | None, slopes: np.ndarray | None, notes: list) -> Layout:
    """As elab_lib trims them: the reconstructor's non-zero rows are the modes, up to the last
    one (the gains are g_gain[0:max(modes_idx)]: aorecmatrix__define.pro:36-61,
    aocontrol__define.pro:151-168), rows past nmodes_filter being IIR states (IirHeader); its
    non-zero columns the valid slopes (the first 2 nsub: aoslopes__define.pro:98-155).  Without
    a reconstructor, the columns up to the last that varies over the record."""
    if rec is None:
        n_modes, n_slopes = _last_varying(modes), _last_varying(slopes)
        if n_slopes is not None:
            n_slopes += n_slopes % 2
        for name, n, data in (("command_modes", n_modes, modes), ("slopes", n_slopes, slopes)):
            if data is not None and n is not None and n < data.shape[1]:
                notes.append(Note(name, f"{data.shape[1] - n} padding columns of {data.shape[1]} left out (constant over the record)"))
        return Layout(n_modes, n_slopes)
    iir = IirHeader.of(rec_keys) if rec_keys is not None else None
    rows = np.flatnonzero(np.any(rec != 0, axis=1))
    columns = np.flatnonzero(np.any(rec != 0, axis=0))
    if iir is not None and len(rows) and rows.max() >= iir.n_modes_filter:
        spare = rows[rows >= iir.n_modes_filter]
        rows = rows[rows < iir.n_modes_filter]
        notes.append(
            Note(
                "command_modes",
                f"modal rows {spare.min() + 1}-{spare.max() + 1} carry the IIR states of modes "
                f"{', '.join(str(m + 1) for m in iir.modes)} (reconstructor header MODEIDXN, IIRNELE0): left out",
            )
        )
    if not len(rows) or not len(columns):
        raise InputError(f"{rec_keys.where if rec_keys is not None else 'the reconstructor'} is all zeros: it holds no mode")
    n_modes, n_slopes = int(rows.max()) + 1, int(columns.max()) + 1
    n_slopes += n_slopes % 2
    holes = n_modes - len(rows)
    if holes:
        notes.append(Note("reconstructor", f"{holes} of modes 1-{n_modes} have no reconstructor row (kept, as elab_lib keeps them)"))
    for name, data, n in (("command_modes", modes, n_modes), ("slopes", slopes, n_slopes)):
        if data is not None and data.shape[1] > n:
            notes.append(Note(name, f"columns {n + 1}-{data.shape[1]} are padding (beyond the reconstructor's): left out"))
    return Layout(n_modes, n_slopes, iir)


def read_lbt(path: str | Path, required: tuple[str, ...] = REQUIRED) -> TelemetryReader:
    """An LBT TN folder as soulctl's model (see the module); InputError naming the file."""
    folder = Path(path)
    if not folder.is_dir():
        raise InputError(f"telemetry folder {path} is not a folder")
    tn = tracking_number(folder)
    notes: list[Note] = []
    counter = _frame_counter(folder, tn)
    frames = counter.size
    arrays: dict = {"frame_counter": counter.astype(np.int64) - int(counter[0])}
    wfs = _wfs_keywords(folder, notes)
    attributes: dict = dict(LBT_SYSTEM)
    rate = _rate(wfs, folder, tn, counter.astype(np.int64), notes)
    if rate is not None:
        attributes["rate_hz"] = rate
        arrays["frame_time_s"] = arrays["frame_counter"] / rate
    delay = _delay(wfs, rate, notes)
    if delay is not None:
        attributes["delay_frames"] = delay
    reflcoef = 4.0 if (mode := operation_mode(wfs, tn)) == "RR" else 2.0
    sav = AdsecSav(folder, notes)
    rec, rec_keys = _reconstructor(folder, sav, notes)
    slopes = _series(folder, "Slopes", tn, frames)
    series = {name: _series(folder, stem, tn, frames) for stem, name in SERIES.items()}
    layout = _layout(rec, rec_keys, series["command_modes"], slopes, notes)
    if slopes is not None:
        slopes = slopes[:, : layout.n_slopes]
        if slopes.shape[1] % 2:
            raise InputError(f"telemetry folder {folder}: Slopes_{tn}.fits has {slopes.shape[1]} columns, expected x, y pairs")
        arrays["slopes"] = deinterleaved(slopes)
    scale = NM_PER_M * reflcoef
    notes.append(Note("", f"operation mode {mode} (elab_lib's rule, aoelab__define.pro:119-166): modes and commands x {scale:g} nm per m"))
    for name, data in series.items():
        if data is not None:
            arrays[name] = (data[:, : layout.n_modes] if name == "command_modes" else data) * scale
    _gains(folder, tn, sav, layout.n_modes, arrays)
    if rec is not None:
        r = rec[: layout.n_modes, : layout.n_slopes]
        arrays["reconstructor"] = deinterleaved(r.astype(np.float64)) * RECONSTRUCTOR_NM_PER_M
        if "slopes" in arrays and r.shape[1] == arrays["slopes"].shape[1]:
            arrays["measured_modes"] = arrays["slopes"] @ arrays["reconstructor"].T
    extras = folder / f"soulctl_{tn}.fits"
    _extras(extras, arrays, attributes)
    if "controller_num" not in arrays:  # a folder soulctl wrote holds its exact filters
        _controller(layout, arrays, notes)
    for name in ("gains", "command_modes", "measured_modes"):
        if name in arrays:
            attributes.setdefault("n_modes", np.shape(arrays[name])[-1])
            break
    unit = {} if extras.exists() else {"slopes_unit": "LBT slope units (normalised)"}
    return TelemetryReader.from_arrays(path, arrays, attributes, required, tuple(notes), **unit)


def _frame_counter(folder: Path, tn: str) -> np.ndarray:
    """FramesCounter_<TN>.fits: a 1-D counter of whole frame numbers, at least one frame."""
    counter, _ = _read_fits(folder / f"FramesCounter_{tn}.fits")
    if counter is None or counter.ndim != 1 or counter.size < 1 or counter.dtype.kind not in "iuf":
        raise InputError(f"telemetry folder {folder}: FramesCounter_{tn}.fits must hold a 1-D frame counter (numbers) of at least 1 frame")
    if not np.all(np.isfinite(counter) & (counter == np.floor(counter)) & (np.abs(counter) < 2**62)):
        raise InputError(f"telemetry folder {folder}: FramesCounter_{tn}.fits must hold whole frame numbers (no NaN)")
    return counter


def _gains(folder: Path, tn: str, sav: AdsecSav, n_modes: int | None, arrays: dict) -> None:
    """adsec.sav's g_gain, else soulctl's Gains_<TN>.fits, cut to the record's modes."""
    gains = sav.gains
    if gains is None and (folder / f"Gains_{tn}.fits").exists():
        data, _ = _read_fits(folder / f"Gains_{tn}.fits")
        gains = None if data is None else np.asarray(data, dtype=float).ravel()
    if gains is not None:
        arrays["gains"] = gains[:n_modes] if n_modes is not None else gains


def _controller(layout: Layout, arrays: dict, notes: list[Note]) -> None:
    """The recorded IIR filters and forgetting factors, when the reconstructor's header holds
    them; the recorded gains scaled by each filter's numerator (the schema's unit filters)."""
    n_modes = layout.n_modes
    if layout.iir is None or n_modes is None:
        notes.append(Note("controller_num", "the folder does not hold the modes' time filters (A_delay is in the calibration tree)"))
        return
    filters = layout.iir.controller(n_modes)
    if filters is None:
        notes.append(Note("controller_num", "the reconstructor's IIR keywords do not map onto its modes: time filters unknown"))
        return
    arrays["controller_num"], arrays["controller_den"], scale = unit_coefficients(*filters)
    if "gains" in arrays and np.any(scale != 1.0):
        arrays["gains"] = arrays["gains"] * scale  # the loop gain of a filter whose numerator is not monic
        notes.append(Note("gains", "g_gain times the IIR numerators' first coefficients (the loop gains of those filters)"))


EXTRA_TEXTS = ("configuration", "run_description", "status", "partial_reason", "soulctl_version", "sensor", "corrector", "telescope")
EXTRA_INTEGERS = ("schema_version", "telemetry_every", "diverged_at", "n_modes")
EXTRA_REALS = ("telescope_diameter_m", "telescope_obstruction_m")


def _extras(path: Path, arrays: dict, attributes: dict) -> None:
    """soulctl's own records of a folder it wrote (InputError naming the file if damaged); a
    record of another system keeps what it says of its system (LBT's otherwise)."""
    if not path.exists():
        return
    try:
        with fits.open(path, memmap=False) as hdus:
            tagged = [(h.header[EXTRA_KEY], h.data) for h in hdus if EXTRA_KEY in h.header]
        if any(name == "sensor" for name, _ in tagged):  # written since records state their system: only what it states
            for key in LBT_SYSTEM:
                attributes.pop(key, None)
        for name, data in tagged:
            if data is None:
                raise ValueError(f"HDU {name} holds no data")
            data = np.asarray(data)
            if name in EXTRA_TEXTS:
                attributes[name] = bytes(data.astype(np.uint8)).decode("utf-8")
            elif name in EXTRA_INTEGERS:
                attributes[name] = int(data.ravel()[0])
            elif name in EXTRA_REALS:
                attributes[name] = float(data.ravel()[0])
            else:
                arrays[name] = data
    except (OSError, ValueError, TypeError, IndexError, UnicodeDecodeError) as e:
        first = " ".join(str(e).split()).split(". ")[0][:160]
        raise InputError(f"telemetry folder {path.parent}: {path.name} is not a readable soulctl record ({first})") from None


# ----------------------------------------------------------------------------------------- writing

ON_SKY_NM_PER_M = NM_PER_M * 2.0  # reflcoef 2: what elab_lib takes for a folder whose telescope tracks
UNKNOWN_NUMBER, UNKNOWN_TEXT = "-9999", "UNKNOWN"  # the supervisor's (WfsArbScripts.py:440-441)
# The keywords elab_lib reads of a SOUL wfs.fits, besides the camera's, soulctl knows nothing of
# in a simulation: written as the supervisor writes an unknown value.
UNKNOWN_KEYWORDS = (
    "stagex.POSITION", "stagey.POSITION", "stagez.POSITION", "rerot.POSITION", "lens.POSITION_X", "lens.POSITION_Y",
    "adc1.POSITION", "adc2.POSITION", "lamp.INTENSITY", "cuberot.POSITION", "cubestage.POSITION", "sc.OPTG",
    "sc.NCPA_TRIGGER", "RR.MODE", "ocam2.READOUT_SPEED", "ocam2.EM_GAIN",
)  # fmt: skip
UNKNOWN_TEXTS = ("ocam2.STATUS", "ocam2.DARK_FILENAME", "sc.SLOPENULL", "sc.PUPILS")


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
    counter = counter.astype(np.int32) if counter.size and counter.max() < 2**31 else counter  # the writer's TINT where it fits
    fits.PrimaryHDU(counter).writeto(folder / f"FramesCounter_{tn}.fits")
    if "slopes" in arrays:
        fits.PrimaryHDU(interleaved(np.asarray(arrays["slopes"], dtype=np.float32))).writeto(folder / f"Slopes_{tn}.fits")
    for stem, name in SERIES.items():
        if name in arrays:
            fits.PrimaryHDU((np.asarray(arrays[name]) / ON_SKY_NM_PER_M).astype(np.float32)).writeto(folder / f"{stem}_{tn}.fits")
    if "mirror_modes" in arrays and "modes_to_commands" in arrays:
        positions = np.asarray(arrays["mirror_modes"]) @ np.asarray(arrays["modes_to_commands"]).T / ON_SKY_NM_PER_M
        fits.PrimaryHDU(positions.astype(np.float32)).writeto(folder / f"Positions_{tn}.fits")
    fits.PrimaryHDU(header=wfs_header(attributes, configuration)).writeto(folder / "wfs.fits")
    if "gains" in arrays:
        fits.PrimaryHDU(np.asarray(arrays["gains"], dtype=np.float32)).writeto(folder / f"Gains_{tn}.fits")
    if "reconstructor" in arrays:
        r = interleaved(np.asarray(arrays["reconstructor"]) / RECONSTRUCTOR_NM_PER_M)
        fits.PrimaryHDU(r.astype(np.float32)).writeto(folder / f"Rec_{tn}.fits")
    _write_extras(folder / f"soulctl_{tn}.fits", arrays, attributes, configuration)


def wfs_header(attributes: dict, configuration: dict) -> fits.Header:
    """wfs.fits of a soulctl record, as elab_lib reads a SOUL one: the OCAM2K's keywords
    (aoocam2k__define.pro:14-31; ocam2.MODE makes it SOUL, aowfs_status__define.pro:125-127),
    the mode whose read-out time is soulctl's delay model's (so that computeDelay sees the
    camera soulctl models), the modulation, a tracking telescope (ONSKY: m of surface x 2e9),
    a SOUL unit (aowfs_status:211-221), the other keywords elab_lib reads as the supervisor
    writes unknown values, and soulctl's delay in frames (SOULDLY)."""
    header = fits.Header()
    cards: dict = {"W_UNIT": "W1SOUL", "tel.TEL.ISTRACKING": 1, "sc.DISTURBANCE": 0, "sc.PIXELS_DECIMATION": 0}
    cards |= {k: UNKNOWN_NUMBER for k in UNKNOWN_KEYWORDS} | {k: UNKNOWN_TEXT for k in UNKNOWN_TEXTS}
    cards["ocam2.MODE"] = 1 + int(np.argmin([abs(t - DelayModel.from_table("soul").t_readout_ms * 1e-3) for t in SOUL_READOUT_S]))
    cards["sc.SLOPES_DECIMATION"] = int(attributes.get("telemetry_every", 1)) - 1
    if "rate_hz" in attributes:
        cards["ocam2.FRAMERATE"] = float(attributes["rate_hz"])
    binning = nested(configuration, "observation", "wfs", "binning", number=True)
    cards["ocam2.BINNING"] = int(binning) if binning is not None else UNKNOWN_NUMBER
    modulation = nested(configuration, "observation", "wfs", "modulation_lambda_over_d", number=True)
    cards[MODULATION_KEYWORD] = float(modulation) if modulation is not None else UNKNOWN_NUMBER
    for key in sorted(cards):  # sorted, as the supervisor writes them (fits_lib.py:46)
        header[f"HIERARCH {key}"] = cards[key]
    if "delay_frames" in attributes:
        header[DELAY_KEYWORD] = (float(attributes["delay_frames"]), "loop delay [frames] (soulctl)")
    return header


def _frames(arrays: dict) -> int:
    return next((len(v) for k, v in arrays.items() if k in ("measured_modes", "command_modes", "slopes", "commands")), 0)


LBT_HELD = ("frame_counter", "frame_time_s", "slopes", "command_modes", "commands", "gains", "reconstructor")


def _write_extras(path: Path, arrays: dict, attributes: dict, configuration: dict) -> None:
    hdus = fits.HDUList([fits.PrimaryHDU()])
    for name, data in arrays.items():
        if name not in LBT_HELD or name in ("command_modes", "commands", "gains", "reconstructor"):  # exact copies (LBT's are float32)
            hdus.append(tagged_hdu(name, np.asarray(data)))
    system = {k: attributes[k] for k in LBT_SYSTEM if k in attributes} or {"sensor": "unknown"}  # "sensor": says it states its system
    texts = {"configuration": json.dumps(configuration)} | {k: str(v) for k, v in (attributes | system).items() if k in EXTRA_TEXTS[1:]}
    for name, text in texts.items():
        hdus.append(tagged_hdu(name, np.frombuffer(text.encode("utf-8"), dtype=np.uint8)))
    for name in EXTRA_INTEGERS:
        if name in attributes:
            hdus.append(tagged_hdu(name, np.array([int(attributes[name])], dtype=np.int64)))
    for name in EXTRA_REALS:
        if name in attributes:
            hdus.append(tagged_hdu(name, np.array([float(attributes[name])], dtype=np.float64)))
    hdus.writeto(path)
