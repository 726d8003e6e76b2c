"""LBT tracking-number folders as LBT's supervisor writes them, written here with astropy and
an IDL save file alone (not soulctl's writer), each detail from the writer's public code
(icprog/MagAO, snapshot 3d5b87d):

* OptLoopDiagnostic.cpp:837-939 (endSaving): one primary HDU per file, the per-frame vector
  along NAXIS1 - Slopes (frames, 1600) float32 padded beyond the valid slopes, Modes,
  Commands and Positions (frames, 672) float32, the counters (frames,) 32-bit integers
  (TINT -> BITPIX 32, lib/iolib.c:441-457);
* wfs.fits (WfsArbScripts.py:416-727, 1608-1617; fits_lib.py:46-47): a header-only HDU of
  sorted HIERARCH cards, numbers as text ('%5.2f' % framerate), '-9999' for values the
  supervisor did not know, 'UNKNOWN' for unknown states; tel.* values as str(value);
* adsec.sav (fsm_savestatus.pro:5-21): g_gain, 672 per-mode gains, and the structure status
  whose b0_a names the reconstructor;
* the reconstructor Rec_<x>.fits (intmatlib.cpp:369, gen_reconstructor_gui.pro:89-93):
  (672, 1600) zero-padded, m of surface per slope unit; elab_lib reads it from the
  calibration tree, soulctl from the folder.

The loop itself is ``foreign_records.modal_loop``: integrators on chi z^-d with the delay
elab_lib's computeDelay gives for the camera and rate, so that identification can be checked.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from astropy.io import fits
from foreign_records import modal_loop
from idl_save import write_sav

ACTUATORS = 672
SLOPES = 1600
ON_SKY_M_PER_NM = 1 / 2e9  # Modes, Commands: nm of wavefront -> m of surface (reflcoef 2, elab_lib aomodes:31)
REC_M_PER_NM = 1 / 4e9  # R s: x 1e9 x reflcoef x 2 on sky (aoresidual_modes__define.pro:40-44)
FLAO_DELAY_FRAMES = (1 / 990.0 + 0.95e-3 + 0.72e-3 + 0.5e-3) * 990.0  # computeDelay, ccd39 binning 1 at 990 Hz
SOUL_DELAY_FRAMES = (1 / 500.0 + 0.24e-3 + 0.66e-3 + 0.5e-3) * 500.0  # computeDelay, ocam2 mode 2 at 500 Hz: 1.70


def wfs_cards(camera: str = "ccd39", rate_text: str = "990.00", extra: dict | None = None) -> dict:
    """wfs.fits's keys as getSetupFits writes them (numbers as text where it formats them)."""
    cards = {
        "W_UNIT": "W1",
        "SENSOR": "WFS",
        "INSTR": "LUCI",
        f"{camera}.STATUS": "STATE_OPERATING",
        f"{camera}.FRAMERATE": rate_text,  # '%5.2f' % framerate (WfsArbScripts.py:480)
        f"{camera}.READOUT_SPEED": "-9999",
        f"{camera}.BINNING": 1,
        f"{camera}.DARK_FILENAME": "UNKNOWN",
        "tt.STATUS": "STATE_OPERATING",
        "tt.LAMBDA_D": 3.0,
        "stagex.POSITION": "-9999",
        "lamp.STATUS": "UNKNOWN",
        "lamp.INTENSITY": "-9999",
        "sc.DECIMATION": 0,
        "tel.TEL.ISTRACKING": "1",  # str(value) of the RTDB variable (WfsArbScripts.py:693-712)
        "tel.TEL.EL": "-9999",  # older than 120 s
    }
    if camera == "ocam2":
        cards["ocam2.MODE"] = 2
    return cards | (extra or {})


def write_header_only(path: Path, cards: dict) -> None:
    header = fits.Header()
    for key in sorted(cards):  # fits_lib.py:46: sorted, each as HIERARCH <key>
        header[f"HIERARCH {key}"] = cards[key]
    fits.PrimaryHDU(header=header).writeto(path)


def write_real_folder(
    root: Path,
    tn: str = "20190302_190223",
    frames: int = 3000,
    n_modes: int = 10,
    n_slopes: int = 40,
    chi: float = 0.8,
    delay: float = FLAO_DELAY_FRAMES,
    cards: dict | None = None,
    rec_header: dict | None = None,
    reconstructor: bool = True,
    seed: int = 3,
) -> tuple[Path, dict]:
    """A folder of ``n_modes`` modes and ``n_slopes`` valid slopes in the writer's padded
    layout, and its truth (the modes in nm, the gains, chi, the delay)."""
    folder = root / f"Data_{tn}"
    folder.mkdir(parents=True)
    gains = np.full(n_modes, 0.4)
    gains[:2] = 0.3
    m, c = modal_loop(frames, gains, [1.0], [1.0, -1.0], delay, chi, seed=seed, noise=2.0)
    rng = np.random.default_rng(seed)
    r_valid = rng.standard_normal((n_modes, n_slopes)) / n_slopes  # nm of R s per slope unit, / 4e9 on disk
    slopes_valid = m @ np.linalg.pinv(r_valid).T  # slopes whose R s is m
    rec = np.zeros((ACTUATORS, SLOPES), np.float32)
    rec[:n_modes, :n_slopes] = r_valid * REC_M_PER_NM
    slopes = np.zeros((frames, SLOPES), np.float32)
    slopes[:, :n_slopes] = slopes_valid  # interleaved x, y is the reader's business: R's columns follow them
    modes = np.zeros((frames, ACTUATORS), np.float32)
    modes[:, :n_modes] = c * ON_SKY_M_PER_NM
    commands = (rng.standard_normal((ACTUATORS, n_modes)) @ c.T).T * ON_SKY_M_PER_NM
    counter = (np.arange(frames) + 123456).astype(np.int32)
    fits.PrimaryHDU(counter).writeto(folder / f"FramesCounter_{tn}.fits")
    for name in ("MirrorCounter", "SkipCounter", "PendingCounter", "WFSGlobalTimeout", "FlTimeout", "CrcErrors", "Timestamp"):
        fits.PrimaryHDU(np.zeros(frames, np.int32)).writeto(folder / f"{name}_{tn}.fits")
    fits.PrimaryHDU(np.ones(frames, np.int32)).writeto(folder / f"LoopClosed_{tn}.fits")
    fits.PrimaryHDU(slopes).writeto(folder / f"Slopes_{tn}.fits")
    fits.PrimaryHDU(modes).writeto(folder / f"Modes_{tn}.fits")
    fits.PrimaryHDU(commands.astype(np.float32)).writeto(folder / f"Commands_{tn}.fits")
    fits.PrimaryHDU(commands.astype(np.float32)).writeto(folder / f"Positions_{tn}.fits")
    write_header_only(folder / "wfs.fits", wfs_cards() if cards is None else cards)
    g_gain = np.zeros(ACTUATORS, np.float32)
    g_gain[:n_modes] = gains
    rec_name = "Rec_20181217_031744.fits"
    write_sav(folder / "adsec.sav", {"g_gain": g_gain}, {"status": {"b0_a": f"adsec_calib/RECs/{rec_name}", "m2c": "M2C/KL/m2c.fits"}})
    if reconstructor:
        header = fits.Header()
        for key, value in (rec_header or {}).items():
            header[key] = value
        fits.PrimaryHDU(rec, header=header).writeto(folder / rec_name)
    return folder, {"measured": m, "commands": c, "gains": gains, "chi": chi, "delay": delay, "slopes": slopes_valid}
