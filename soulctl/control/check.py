"""`soulctl rtc check`: is a per-mode parameter set safe to upload?  For every mode, the loop
of its filter and gain on the plant chi_i z^-d (the 127 Hz structure on Tip/Tilt):
stability, gain margin, phase margin, modulus margin min |1 + L| and maximum stable gain, and
the parameter set's RTC states against the state budget (paper Sec. 2.3: N_I + sum N_f <=
672).

Modes that share a filter shape and plant differ only by g chi in L = g chi L_unit, so the
unit open loop and the maximum stable gain (``transfer.max_stable_gain``, decided on the
closed-loop poles) are computed once per distinct loop and the margins of all modes follow
on the shared frequency grid (``transfer.frequency_grid``): stable iff g chi < g_max, gain
margin g_max / (g chi), modulus margin the grid minimum of |1 + g chi L_unit|, phase margin at
the first crossing of |L| = 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .filters import Filter
from .rtc import SOUL_STATE_SIZE
from .transfer import Loop, Plant, frequency_grid, max_stable_gain

DEFAULT_MODULUS_MARGIN = 0.2  # the paper's epsilon (design constraint |1 + H P| > epsilon)


@dataclass(frozen=True)
class Criteria:
    modulus_margin: float = DEFAULT_MODULUS_MARGIN
    gain_margin: float = 1.0  # > 1: stable with that factor of gain to spare
    phase_margin_deg: float = 0.0


@dataclass(frozen=True)
class ModeCheck:
    mode: int  # 1-based
    gain: float
    chi: float
    stable: bool
    gain_margin: float
    phase_margin_deg: float | None
    modulus_margin: float
    max_stable_gain: float  # of g, at this chi
    passed: bool

    def to_dict(self) -> dict:
        def fin(x):
            return None if x is None or not math.isfinite(x) else float(x)

        return {
            "mode": self.mode, "gain": self.gain, "chi": self.chi, "stable": self.stable,
            "gain_margin": fin(self.gain_margin), "phase_margin_deg": fin(self.phase_margin_deg),
            "modulus_margin": fin(self.modulus_margin), "max_stable_gain": fin(self.max_stable_gain), "passed": self.passed,
        }  # fmt: skip


def _plant(delay_frames: float, structure_ba, tip_tilt: bool) -> Plant:
    if structure_ba is None or not tip_tilt:
        return Plant(delay_frames)
    b, a = structure_ba
    return Plant(delay_frames, 1.0, (tuple(map(float, b)), tuple(map(float, a))))


def _group_checks(unit: Loop, gchi: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, ...]:
    """(stable, gain margin, phase margin, modulus margin, g_max at chi = 1) for the products g chi."""
    g_max = max_stable_gain(unit)
    L1 = unit.open_loop(f)
    L = gchi[:, None] * L1[None, :]
    modulus = np.min(np.abs(1.0 + L), axis=1)
    stable = gchi < g_max
    with np.errstate(divide="ignore"):
        gm = np.where(gchi > 0, g_max / gchi, math.inf)
    above = np.abs(L) >= 1.0
    cross = np.argmax(above[:, :-1] & ~above[:, 1:], axis=1)  # first downward crossing of |L| = 1
    has = (above[:, :-1] & ~above[:, 1:]).any(axis=1)
    pm = np.where(has, 180.0 - np.abs(np.degrees(np.angle(L[np.arange(len(gchi)), cross]))), np.nan)
    pm = np.where(stable, pm, -pm)
    return stable, gm, pm, modulus, np.full(len(gchi), g_max)


def check_modes(
    filters: list[Filter], chi: np.ndarray, delay_frames: float, rate_hz: float, structure_ba, criteria: Criteria
) -> list[ModeCheck]:
    """Every mode's check (see the module); ``filters`` carry the gains."""
    f = frequency_grid(rate_hz)
    keys: dict[tuple, list[int]] = {}
    for i, h in enumerate(filters):
        keys.setdefault((tuple(h.zeros), tuple(h.poles), i < 2 and structure_ba is not None), []).append(i)
    out: list[ModeCheck | None] = [None] * len(filters)
    for (zeros, poles, structured), modes in keys.items():
        unit = Loop(Filter(zeros, poles, 1.0), _plant(delay_frames, structure_ba, structured), rate_hz)
        g = np.array([filters[i].gain for i in modes])
        c = np.asarray(chi)[modes]
        stable, gm, pm, mm, gmax = _group_checks(unit, g * c, f)
        for j, i in enumerate(modes):
            ok = bool(stable[j]) and mm[j] >= criteria.modulus_margin and gm[j] >= criteria.gain_margin
            ok = ok and (math.isnan(pm[j]) or pm[j] >= criteria.phase_margin_deg)
            out[i] = ModeCheck(i + 1, float(g[j]), float(c[j]), bool(stable[j]), float(gm[j]),
                               None if math.isnan(pm[j]) else float(pm[j]), float(mm[j]), float(gmax[j] / c[j]), ok)  # fmt: skip
    return [x for x in out if x is not None]


def state_count(filters: list[Filter]) -> int:
    """RTC states the filters need (one per filter state; paper: N_I + sum N_f)."""
    return sum(h.n_states for h in filters)


STATE_BUDGET = SOUL_STATE_SIZE
