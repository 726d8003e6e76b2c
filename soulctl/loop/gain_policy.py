"""The optimisers' initial gains from the operating point (``initial_gains``): the design
gains capped for stability against the plant model's chi, and lowered where the noise
dominates the model PSD (``noise_aware_gains``).  ``loop.optimize`` and ``LiveOptimisers``
start from them."""

from __future__ import annotations

import math

import numpy as np

from ..control import mgm
from ..control import ogtl as ogtl_model
from ..control.gains import (
    LoopGains,
    capped_gains,
    unit_loops,
)
from ..disturbance.modal_psd import cutoff_hz, modal_psd
from ..disturbance.turbulence import TurbulenceTipTilt
from ..optics.atmosphere import LAMBDA_REF_M, AtmosphereConfig
from ..optics.cache import ArrayCache
from ..optics.calibration import Calibration
from ..optics.pupil import LBT_DIAMETER_M
from .chi_model import optical_gain_table, plant_model
from .run import RunRequest
from .simulation import ClosedLoop

INITIAL_GAIN_FRACTION = 0.5  # initial gains capped at this fraction of the plant model's g_max / chi
MODEL_SEGMENT = 8192  # frequency grid of the model PSD: fine enough for the lowest cut-offs (0.1 Hz at 1700 Hz)


def initial_gains(
    gains: LoopGains,
    request: RunRequest,
    calibration: Calibration,
    cache: ArrayCache,
    loop: ClosedLoop,
    chi: np.ndarray,
    noise: np.ndarray,
    ogtl: bool,
    probe_mode: int,
) -> np.ndarray:
    """The optimisers' starting gains from the operating point: the run's gains capped for
    stability (``capped_gains``) at the larger of each mode's chi in the plant model and its
    chi at the worst seeing (with OGTL, gamma_i / gamma_probe grows as the correction degrades:
    the low orders lose less optical gain than the probed mode), and by ``noise_aware_gains``,
    MGM's optimum on a model of the loop's POL PSD: the turbulence of each mode at the run's
    seeing, L0 and wind, the vibrations on Tip/Tilt, and the WFS noise of the operating point
    (``noise``, ``sensor.modal_noise_nm``) over the optical gains the model expects at the
    run's seeing, for Tip/Tilt and the modes whose noise dominates.  A bright star keeps the
    design gains (lower gains there risk losing the PWFS's lock on a large low-order
    excursion); a faint one starts at the gains its noise allows, so that OGTL raising k
    towards chi = 1 cannot over-drive the noise.  With OGTL the model's optimum caps every
    mode: k of 3-5 turns the design gains of the turbulence-dominated modes into effective
    gains of ~0.7 at the faint end (R15.5, 1.0": "before" 0.03 against 0.12 so capped)."""
    obs = request.observation
    chi_worst = plant_model(calibration, cache, ogtl, probe_mode, ogtl_model.WORST_SEEING_ARCSEC)
    gamma = optical_gain_table(calibration, cache, request.seeing_arcsec)
    capped = capped_gains(
        gains.per_mode(len(chi)), obs, request.structure, np.maximum(chi, chi_worst), gains.forgetting, INITIAL_GAIN_FRACTION
    )
    atmosphere = request.atmosphere()
    model = noise_aware_gains(
        obs,
        request.structure,
        gains.forgetting,
        chi,
        calibration.basis.variance,
        atmosphere,
        noise / gamma,
        request.vibrations,
        1.0 / loop.mas_per_nm_tt,
        every_mode=ogtl,
    )
    return np.minimum(capped, model)


def noise_aware_gains(
    observation,
    structure,
    forgetting: float,
    chi: np.ndarray,
    basis_variance: np.ndarray,
    atmosphere: AtmosphereConfig,
    pol_noise_nm: np.ndarray,
    vibrations=None,
    nm_per_mas: float = 1.0,
    every_mode: bool = False,
) -> np.ndarray:
    """MGM's optimum (Eq. cost) on the model POL PSD for Tip/Tilt and each noise-dominated mode
    (inf for the others: they keep their design gains; ``every_mode``: the optimum for all),
    on a MODEL_SEGMENT grid, over the MGM range (margin included).  A mode is noise-dominated when its turbulence's variance is below
    the noise's (MGM's own rule, ``mgm.noise_dominated``).  The model: white noise of ``pol_noise_nm`` RMS per frame plus the
    turbulence - for Tip/Tilt the frozen-flow Tip/Tilt PSD (``TurbulenceTipTilt`` at the
    effective wind) and the vibrations' lines on that axis (Tip's on mode 1, Tilt's on mode 2;
    their mean on both put the lines' power where it is not: 9 and 6.5 mas at 13 Hz became 7.8
    on each), in nm through ``nm_per_mas``; for the other modes
    the layers' ``modal_psd`` weighted by their Cn^2 (basis variances in rad^2 at 500 nm for
    r0 = 1 m)."""
    rate = observation.frame_rate_hz
    n = len(chi)
    f = np.fft.rfftfreq(MODEL_SEGMENT, 1.0 / rate)[1:]
    unit, ba = unit_loops(observation, structure, forgetting, n)
    L1 = mgm.unit_open_loops(unit, chi, observation.delay_frames, rate, f, ba)
    upper = mgm.gain_limits(unit, chi, observation.delay_frames, rate, mgm.MgmSettings().margin, ba)
    nm2 = np.asarray(basis_variance[:n]) * atmosphere.r0_m ** (-5.0 / 3.0) * (LAMBDA_REF_M * 1e9 / (2 * math.pi)) ** 2
    modes = np.arange(1, n + 1)
    psd = np.repeat((np.asarray(pol_noise_nm) ** 2 / (rate / 2))[:, None], f.size, axis=1)
    for w, layer in zip(atmosphere.weights, atmosphere.layers):
        psd[2:] += modal_psd(f, w * nm2[2:], cutoff_hz(modes[2:], layer.wind_speed_m_s, LBT_DIAMETER_M))
    tt = TurbulenceTipTilt(atmosphere.seeing_arcsec, atmosphere.L0_m, atmosphere.effective_wind_speed_m_s).psd(f)
    for mode, axis in enumerate(("tip", "tilt")):  # mode 1 is Tip, mode 2 Tilt, each with its own lines
        psd[mode] += (tt if vibrations is None else tt + vibrations.psd(f, axis)) * nm_per_mas**2
    g = mgm.optimal_gains(psd, L1, upper)
    signal = np.sum(psd, axis=1) * (f[1] - f[0]) - np.asarray(pol_noise_nm) ** 2 * (f[-1] - f[0]) / (rate / 2)
    noisy = signal < np.asarray(pol_noise_nm) ** 2
    noisy[:2] = True  # Tip/Tilt: its model (turbulence and vibration lines) is trusted whatever its SNR
    return g if every_mode else np.where(noisy, g, np.inf)
