"""`soulctl telemetry identify`: the plant of a recorded loop, in this order (each step uses
the ones before it):

1. the record's window as spectra and moments (``record``);
2. the delay, chi per group and the noise per mode from the noise rejection (``rejection``);
3. with an OGTL probe, chi and d of the probed mode from the probe (``probe``): the probe fixes
   chi's scale, the rejection fit its shape across the groups (``_optical_gains``);
4. the pseudo-open-loop Tip/Tilt and its vibration lines (``lines``);
5. r0 and L0 from the pseudo-open-loop modal variances less the noise (``seeing``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..disturbance.vibrations import VibrationSpectrum
from ..loop.run import calibration_setup
from ..optics.atmosphere import r0_from_seeing
from ..optics.cache import ArrayCache, EntrySpec, cache_key
from ..optics.calibration import controlled_basis
from ..telemetry.figures import pseudo_open_loop
from . import seeing
from .lines import LIMIT_HZ, LineEstimate, LineSearch, search_lines
from .plant import OpticalGainGroup, PlantModel, Turbulence, chi_per_mode
from .probe import ProbeFit, fit_probe
from .record import LoopRecord, pol_variance, read_record
from .rejection import RejectionFit, fit_rejection, tip_tilt_noise

REJECTION_METHOD = "Whittle fit of the measured-mode PSDs above f_low to sigma^2 |S(f; d, chi)|^2 with the recorded controller"
PROBE_METHOD = "chi of the probed mode from the OGTL probe (M/C = -chi z^-d), the other groups scaled by the rejection fit's ratios"


@dataclass
class Identification:
    plant: PlantModel
    rejection: RejectionFit
    probe: ProbeFit | None
    lines: list[LineEstimate]
    record: LoopRecord
    pol_variance_nm2: np.ndarray
    model_variance_nm2: np.ndarray | None  # von Karman at the identified r0, L0
    line_psd: tuple[np.ndarray, np.ndarray]  # (f, mean PSD of the pseudo-open-loop Tip/Tilt, mas^2/Hz)
    seconds: dict = field(default_factory=dict)
    not_estimated: dict = field(default_factory=dict)  # figure -> why the record cannot give it
    line_limit: dict | None = None  # the weakest line the search could find (``LineSearch.limit_mas``), where and at what resolution

    def _lines_window(self) -> dict:
        skip = _skipped(self.plant.delay.value)
        return {"first_frame": self.record.tip_tilt_first_frame + skip, "frames": len(self.record.tip_tilt[0]) - skip}

    def to_dict(self) -> dict:
        p = self.plant
        return {
            "telemetry": self.record.path,
            "window": {"first_frame": self.record.first_frame, "frames": self.record.frames, "seconds": self.record.frames / p.rate_hz},
            "lines_window": self._lines_window(),
            "rate_hz": p.rate_hz,
            "sensitivity": self.record.sensitivity,
            "delay_frames": p.delay.to_dict() | {"method": p.delay_method, "recorded": _finite(self.record.delay_frames)},
            "optical_gains": [
                {"modes": f"{g.first_mode}-{g.last_mode}", "chi": g.chi, "sigma": _finite(g.sigma)} for g in p.optical_gains
            ],
            "optical_gain_method": p.optical_gain_method,
            "rejection_fit_chi": [
                {"modes": f"{lo}-{hi}", **c.to_dict(), "change_per_percent_excess": e}
                for (lo, hi), c, e in zip(self.rejection.groups, self.rejection.chi, self.rejection.excess_sensitivity)
            ],
            "probe": None if self.probe is None else {
                "mode": self.probe.mode, "frequency_hz": self.probe.frequency_hz,
                "chi": self.probe.chi.to_dict(), "delay_frames": self.probe.delay.to_dict(),
            },
            "noise_nm2": [None if not math.isfinite(x) else float(x) for x in (p.noise_nm2 if p.noise_nm2 is not None else [])],
            "tip_tilt_noise_mas": _finite(p.tip_tilt_noise_mas),
            "turbulence": None if p.turbulence is None else {
                "seeing_arcsec": p.turbulence.seeing_arcsec, "seeing_sigma": _finite(p.turbulence.seeing_sigma),
                "L0_m": p.turbulence.L0_m, "L0_sigma": _finite(p.turbulence.L0_sigma), "wind_m_s": p.turbulence.wind_m_s,
            },
            "vibration_lines": [
                {"frequency_hz": x.frequency.to_dict(), "damping": x.damping, "tip_mas": x.tip.to_dict(), "tilt_mas": x.tilt.to_dict()}
                for x in self.lines
            ],
            "vibration_line_limit": self.line_limit,
            "not_estimated": self.not_estimated,
            "notes": list(p.notes),
            "seconds": self.seconds,
        }  # fmt: skip


def _finite(x: float | None) -> float | None:
    return None if x is None or not math.isfinite(float(x)) else float(x)


def _optical_gains(rej: RejectionFit, probe: ProbeFit | None) -> tuple[tuple[OpticalGainGroup, ...], str]:
    """Per group chi: the rejection fit's, or with a probe the probe's scale on the fit's shape;
    Tip/Tilt takes the nearest group's where the fit left it out."""
    scale, rel = 1.0, 0.0
    used = probe is not None and math.isfinite(probe.chi.value) and probe.chi.value > 0
    if probe is not None and used:
        inside = [i for i, (lo, hi) in enumerate(rej.groups) if lo <= probe.mode <= hi] or [0]
        ref = rej.chi[inside[0]]
        scale = probe.chi.value / ref.value
        rel = math.hypot(probe.chi.sigma / probe.chi.value, ref.sigma / ref.value)
    groups = tuple(
        OpticalGainGroup(lo, hi, c.value * scale, c.value * scale * math.hypot(c.sigma / c.value, rel))
        for (lo, hi), c in zip(rej.groups, rej.chi)
    )
    if groups[0].first_mode > 1:  # Tip/Tilt: the nearest group's (not fitted)
        tt = groups[0]
        groups = (OpticalGainGroup(1, 2, tt.chi, tt.sigma),) + groups
    return groups, PROBE_METHOD if used else REJECTION_METHOD


WEAK_PER_PERCENT = 0.02  # a group whose chi moves by more than 2 % per 1 % of coloured excess is flagged


def _weak_groups(rej: RejectionFit) -> tuple[str, ...]:
    """A note naming the groups whose chi a small coloured excess of the noise would bias: the
    loop gain there is too low to shape |S| (docs/physics.md, "Identification from telemetry")."""
    weak = [f"{lo}-{hi}" for (lo, hi), e in zip(rej.groups, rej.excess_sensitivity) if abs(e) > WEAK_PER_PERCENT]
    if not weak:
        return ()
    return (
        f"chi of modes {', '.join(weak)} weakly identified: 1 % of coloured excess in the noise (aliasing, turbulence above "
        f"{rej.f_low_hz:.0f} Hz) moves it by more than {100 * WEAK_PER_PERCENT:.0f} % (their loop gain barely shapes |S|); "
        "a probe on one of these modes measures it",
    )


RING_DOWN = 64  # frames of the structural resonance's start-up left out of the pseudo-open loop


def _skipped(d: float) -> int:
    """Leading frames of the pseudo-open-loop Tip/Tilt left out: those whose delayed commands
    come from before the window, and the resonance's ring-down."""
    return int(d) + 1 + RING_DOWN


def _vibrations(record: LoopRecord, d: float, chi_tt: float) -> LineSearch:
    """The lines of the pseudo-open-loop Tip/Tilt, over the frames since the last change of the
    gains (m divided by each frame's k; OGTL's k need not have settled)."""
    m, c = record.tip_tilt
    pol = pseudo_open_loop(m / chi_tt, c, d, record.structure_ba)
    return search_lines(pol[_skipped(d) :] / record.loop.nm_per_mas, record.rate_hz)


def _turbulence(
    record: LoopRecord, whole: np.ndarray, d: float, chi: np.ndarray, noise: np.ndarray, cache: ArrayCache, missing: dict
) -> tuple[Turbulence, np.ndarray]:
    """Seeing and L0 from the pseudo-open-loop variances less the noise (``whole``, over the
    window), corrected for the record's length by its halves' (``seeing.record_length``); L0
    into ``missing`` where the record is too short for it."""
    first, second = (pol_variance(record, d, chi, mo) - np.nan_to_num(noise) / chi**2 for mo in record.half_moments)
    variance, n_low = seeing.record_length(whole, 0.5 * (first + second))
    L0s: tuple[float, ...]
    if record.description is None:
        table, L0s = seeing.noll_variances(record.n_modes, record.loop.diameter_m), (seeing.UNKNOWN_L0_M,)
        missing["L0"] = "a foreign modal basis: the seeing is fitted to Kolmogorov's variances of its radial orders, without L0"
    else:
        setup = calibration_setup(record.description.request())  # its basis and pupil, not its sensing
        L0s = seeing.L0_GRID
        key = cache_key("von-karman-modal-variances", {"calibration": setup.key(), "L0": list(L0s)})
        hit = cache.load(key, EntrySpec({"variances": (len(L0s), record.n_modes)}))
        if hit is not None:
            table = hit["variances"]
        else:
            table = seeing.basis_variances(controlled_basis(setup, cache), setup.pyramid.pupil, L0s)
            cache.store(key, {"variances": table})
    t = seeing.fit_turbulence(variance, table, L0s, n_low)
    r0 = r0_from_seeing(t.seeing_arcsec)
    best = table[L0s.index(t.L0_m)] if t.L0_m in L0s else table[0]
    if len(L0s) > 1 and n_low < seeing.MIN_CORRELATION_TIMES:
        missing["L0"] = (
            f"the record's {record.frames / record.rate_hz:.3g} s span ~{n_low:.0f} correlation times of modes {seeing.LOW_MODES} "
            f"(their variance over half the record against the whole); L0 needs {seeing.MIN_CORRELATION_TIMES:g} or more: "
            "record longer (the lowest orders decorrelate over ~D/wind)"
        )
        t = replace(t, L0_m=seeing.UNKNOWN_L0_M, L0_sigma=math.inf)
    return t, best * r0 ** (-5 / 3) * seeing.NM_PER_RAD**2


MIN_SEEING_MODES = 20  # the seeing fit (modes 3 to half the record's) needs a few radial orders: 3-10 at least


def identify(
    path: str | Path, delay_frames: float | None = None, cache: ArrayCache = ArrayCache(None), structure: str = "auto"
) -> Identification:
    """The plant of the record at ``path`` (see the module); what the record cannot give is
    None with the reason in ``not_estimated``."""
    clock = {"start": time.perf_counter()}
    record = read_record(path, delay_frames, structure)
    clock["read"] = time.perf_counter()
    rej = fit_rejection(record)
    probe = fit_probe(record, rej.delay.value)
    groups, method = _optical_gains(rej, probe)
    clock["delay_and_gains"] = time.perf_counter()
    chi = chi_per_mode(groups, record.n_modes)
    noise = rej.noise_nm2.copy()
    missing: dict[str, str] = {}
    lines: list[LineEstimate] = []
    f_lines, p_lines, limit = np.zeros(0), np.zeros(0), None
    if record.n_modes >= 2:
        search = _vibrations(record, rej.delay.value, float(chi[0]))
        lines, f_lines, p_lines = search.lines, search.f, search.mean_psd
        limit = {"rms_mas": search.limit_mas, "at_hz": LIMIT_HZ, "resolution_hz": search.resolution_hz}
    else:
        missing["vibration_lines"] = missing["tip_tilt_noise_mas"] = "the record holds one mode, not the Tip/Tilt pair"
    clock["vibrations"] = time.perf_counter()
    variance = pol_variance(record, rej.delay.value, chi) - np.nan_to_num(noise) / chi**2
    turbulence, model_variance = None, None
    if record.n_modes >= MIN_SEEING_MODES:
        turbulence, model_variance = _turbulence(record, variance, rej.delay.value, chi, noise, cache, missing)
    else:
        missing["turbulence"] = f"seeing and L0 need modes beyond Tip/Tilt (at least {MIN_SEEING_MODES}; the record holds {record.n_modes})"
    clock["turbulence"] = time.perf_counter()
    tt_noise = None
    if record.n_modes >= 2:
        if rej.groups[0][0] > 1:
            noise[:2] = tip_tilt_noise(record, rej.delay.value, float(chi[0]))
        tt_noise = math.sqrt(noise[0]) / chi[0] / record.loop.nm_per_mas  # referred to the wavefront: what filter design takes
    notes = _notes(record, rej) + _weak_groups(rej)
    spectrum = VibrationSpectrum(tuple(x.line() for x in lines), f"identified from {record.path}") if lines else None
    in_use = record.filters[0].with_gain(float(np.mean(record.gains[:2])) * record.sensitivity)  # g k
    plant = PlantModel(
        record.path, record.rate_hz, rej.delay, REJECTION_METHOD, groups, method, noise, tt_noise, turbulence, spectrum, notes, in_use
    )
    seconds = {k: clock[k] - clock["start"] for k in ("read", "delay_and_gains", "vibrations", "turbulence")}
    return Identification(plant, rej, probe, lines, record, variance, model_variance, (f_lines, p_lines), seconds, missing, limit)


def _notes(record: LoopRecord, rej: RejectionFit) -> tuple[str, ...]:
    """What the identification assumed: the record's loop and how Tip/Tilt's chi was found."""
    tt = (
        "Tip/Tilt chi is the nearest group's: vibrations and the 127 Hz structure keep Tip/Tilt out of the rejection fit"
        if rej.groups[0][0] > 1
        else f"delay and chi from modes 1-{record.n_modes} above {rej.f_low_hz:.0f} Hz (the record holds no other modes)"
    )
    return (tt, "wind speed not estimated", *record.loop.notes)
