"""chi_i of the loop's plant from the optical model: the optical gains gamma_i of the
calibration's modes at a seeing (``optics.optical_gains``, cached), and the plant the optimisers
and the stability checks see with or without OGTL (k gamma_probe = 1 with it, k = 1 without)."""

from __future__ import annotations

import numpy as np

from ..optics.cache import ArrayCache, EntrySpec, cache_key
from ..optics.calibration import Calibration
from ..optics.optical_gains import CHI_TABLE_SEEING_ARCSEC, SCREENS, CorrectionLevel, optical_gains


def optical_gain_table(
    calibration: Calibration, cache: ArrayCache, seeing_arcsec: float = CHI_TABLE_SEEING_ARCSEC, screens: int = SCREENS, seed: int = 1
) -> np.ndarray:
    """gamma_i of the calibration's modes at the reference correction level, cached."""
    key = cache_key("optical-gains", {"calibration": calibration.setup.key(), "seeing": seeing_arcsec, "screens": screens, "seed": seed})
    hit = cache.load(key, EntrySpec({"gains": (calibration.basis.n_modes,)}))
    if hit is not None:
        return hit["gains"]
    gains = optical_gains(calibration, CorrectionLevel(seeing_arcsec), screens, seed).gains
    cache.store(key, {"gains": gains})
    return gains


def mgm_chi(gamma: np.ndarray, ogtl: bool, probe_mode: int) -> np.ndarray:
    """chi_i of MGM's plant: gamma_i / gamma_probe with OGTL (chi = 1 on the probed mode),
    gamma_i (k = 1) without."""
    return gamma / gamma[probe_mode - 1] if ogtl else gamma.copy()


def plant_model(
    calibration: Calibration, cache: ArrayCache, ogtl: bool, probe_mode: int, seeing_arcsec: float = CHI_TABLE_SEEING_ARCSEC
) -> np.ndarray:
    """chi_i of the optimisers' plant: gamma_i / gamma_probe of the reference table with OGTL
    (OGTL holds the probed mode at 1), gamma_i without (k = 1)."""
    return mgm_chi(optical_gain_table(calibration, cache, seeing_arcsec), ogtl, probe_mode)
