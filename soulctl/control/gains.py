"""Loop gains, their one home (paper Sec. 2.3 and Sec. MGM).

* the paper's three groups - Tip/Tilt, modes 3-120, modes 121-last (``gain_groups``) - and a
  gain vector's summary per group;
* ``LoopGains``: the gains a run starts with, per group or per mode (a gain file), and the
  forgetting factor of the leaky integrators; ``mode_filters``: the per-mode filters they give;
* the mapping per mode <-> per RTC state: the diagonal of Delta in zeta(k) = Lambda zeta(k-1)
  + Delta Xi s(k) holds one value per filter state, the mode's gain on each of its states
  (``state_gains``, ``mode_gains``);
* defaults and the stability check on the nominal plant (chi = 1), and capping to the stable
  range of a plant with optical gains chi_i (``capped_gains``);
* the gain file (``read_gain_file``, ``gains_toml``): what `optimize gains --out` writes and
  `loop run --gains FILE` reads.

Gain file formats read (one gain per controlled mode, mode 1 = Tip): TOML ``gains = [g1, g2,
...]`` (what soulctl writes); text/CSV, one gain per line or ``mode,gain`` lines, with an
optional header row naming the columns (``mode,gain`` or ``gain``), '#' starting a comment.
Where modes are given, the gains are placed by their mode number whatever the order of the
lines; every mode from 1 to the last must appear exactly once.  Every gain must be in
``ranges.LOOP_GAIN``; the loop's stability check comes after.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from ..errors import InputError
from ..files import read_input_text, read_toml
from ..ranges import LOOP_GAIN, number_text
from .filters import Filter
from .mgm import gain_limits
from .structure import StructuralResonance, sampled_coefficients, sampled_structure
from .transfer import Loop, Plant, max_stable_gain

MID_GROUP_END = 120  # modes 3-120 (1-based) are the middle group
TIP_TILT = slice(0, 2)  # modes 1-2
DEFAULT_FORGETTING = 0.99  # of the leaky integrators of modes 3..last (proposal)
DEFAULT_IIR_TIP_TILT = 0.69  # the paper's optimised Tip/Tilt gain of its 1700 Hz IIR
SUFFIXES = (".toml", ".txt", ".csv", ".dat")  # of gain files


class LoopSettings(Protocol):
    """What the gains' rules read of an observation (``observation.Observation`` is one): the
    frame rate, the loop delay, the controlled modes and the Tip/Tilt controller."""

    @property
    def frame_rate_hz(self) -> float: ...
    @property
    def delay_frames(self) -> float: ...
    @property
    def modes(self) -> int: ...
    @property
    def tt_control(self) -> str: ...
    @property
    def tt_zeros(self) -> tuple[float, ...]: ...
    @property
    def tt_poles(self) -> tuple[float, ...]: ...
    @property
    def tt_gain(self) -> float | None: ...


def gain_groups(n_modes: int) -> list[tuple[str, slice]]:
    """The paper's three groups (0-based slices), without the empty ones."""
    groups = [
        ("tip-tilt", slice(0, min(TIP_TILT.stop, n_modes))),
        ("modes 3-120", slice(TIP_TILT.stop, min(MID_GROUP_END, n_modes))),
        (f"modes 121-{n_modes}", slice(MID_GROUP_END, n_modes)),
    ]
    return [(name, s) for name, s in groups if s.stop > s.start]


def group_summary(gains: np.ndarray) -> list[dict]:
    """Per paper group: name, modes (1-based), mean, min, max of the gains."""
    return [
        {
            "group": name,
            "modes": f"{m.start + 1}-{m.stop}",
            "mean": float(np.mean(gains[m])),
            "min": float(np.min(gains[m])),
            "max": float(np.max(gains[m])),
        }
        for name, m in gain_groups(len(gains))
    ]


def _check_gain(value: float, name: str) -> None:
    if not LOOP_GAIN.contains(value):
        raise InputError(f"gain {name} must be a number in {LOOP_GAIN.text()}, got {number_text(value)}")


@dataclass(frozen=True)
class LoopGains:
    """The gains a run starts with: one per paper group, or one per mode.

    Parameters
    ----------
    tip_tilt, mid, high : float
        The gains of the paper's groups: Tip/Tilt, modes 3-120, modes 121-last.
    forgetting : float
        The leaky integrators' factor (0..1; 1: pure integrators).
    modes : tuple of float or None
        One gain per mode (a gain file), which overrides the groups; None: the groups.
    """

    tip_tilt: float
    mid: float
    high: float
    forgetting: float = DEFAULT_FORGETTING
    modes: tuple[float, ...] | None = None

    def __post_init__(self):
        for name in ("tip_tilt", "mid", "high"):
            _check_gain(getattr(self, name), name)
        if not (0 <= self.forgetting <= 1):
            raise InputError(f"forgetting factor must be in 0..1, got {number_text(self.forgetting)}")
        if self.modes is not None and not all(LOOP_GAIN.contains(v) for v in self.modes):
            raise InputError(f"per-mode gains must be numbers in {LOOP_GAIN.text()}")

    @classmethod
    def from_modes(cls, gains, forgetting: float = DEFAULT_FORGETTING) -> LoopGains:
        """Per-mode gains; the groups hold their means (for the stability check's names)."""
        g = tuple(float(x) for x in gains)
        if len(g) < TIP_TILT.stop:
            raise InputError(f"a per-mode gain list needs at least the 2 Tip/Tilt gains, got {len(g)}")
        mid = g[TIP_TILT.stop : MID_GROUP_END] or (0.0,)
        high = g[MID_GROUP_END:] or (0.0,)
        return cls(g[0], float(np.mean(mid)), float(np.mean(high)), forgetting, g)

    def per_mode(self, n_modes: int) -> np.ndarray:
        """One gain per mode."""
        if self.modes is not None:
            if len(self.modes) != n_modes:
                raise InputError(f"the gain file has {len(self.modes)} gains but {n_modes} modes are controlled")
            return np.array(self.modes)
        g = np.full(n_modes, self.high)
        g[TIP_TILT.stop : MID_GROUP_END] = self.mid
        g[TIP_TILT] = self.tip_tilt
        return g


def tip_tilt_filter(observation: LoopSettings, gain: float) -> Filter:
    """The observation's Tip/Tilt controller: its IIR (unit-gain zeros/poles times ``gain``) or
    an integrator."""
    if observation.tt_control == "iir":
        return Filter.iir(observation.tt_zeros, observation.tt_poles, gain)
    return Filter.integrator(gain)


def mode_filters(observation: LoopSettings, gains: LoopGains, n_modes: int) -> list[Filter]:
    """Tip/Tilt: ``tip_tilt_filter``; the other modes leaky integrators."""
    g = gains.per_mode(n_modes)
    return [tip_tilt_filter(observation, float(gi)) for gi in g[TIP_TILT]] + [
        Filter.leaky(gains.forgetting, float(gi)) for gi in g[TIP_TILT.stop :]
    ]


def state_gains(blocks: Sequence, n_states: int, gains) -> np.ndarray:
    """The diagonal of Delta for one gain per mode: each mode's gain on each of its filter's
    states (``blocks``: ``rtc.ModeBlock``s; states outside every block stay 0)."""
    g = np.asarray(gains, dtype=float)
    delta = np.zeros(n_states)
    for b in blocks:
        delta[b.offset : b.offset + b.n_states] = g[b.mode]
    return delta


def mode_gains(blocks: Sequence, n_modes: int, delta) -> np.ndarray:
    """One gain per mode read from the diagonal of Delta (0 for uncontrolled modes)."""
    d = np.asarray(delta)
    g = np.zeros(n_modes)
    for b in blocks:
        g[b.mode] = d[b.offset]
    return g


def nominal_loop(observation: LoopSettings, gain: float, tip_tilt: bool, structure: StructuralResonance | None) -> Loop:
    """The loop of one mode as the analysis sees it (chi = 1): Tip/Tilt with the observation's
    filter and the structural resonance, other modes leaky integrators."""
    rate = observation.frame_rate_hz
    d = observation.delay_frames
    if tip_tilt:
        plant = Plant.with_structure(d, structure, rate) if structure is not None else Plant(d)
        return Loop(tip_tilt_filter(observation, gain), plant, rate)
    return Loop(Filter.leaky(DEFAULT_FORGETTING, gain), Plant(d), rate)


def default_gains(observation: LoopSettings, structure: StructuralResonance | None = StructuralResonance()) -> LoopGains:
    """Tip/Tilt: a designed IIR's own gain (``Observation.tt_gain``, from a designed roots
    table), else 0.69 with the IIR (the paper's optimised 1700 Hz gain) capped at 0.7 of its
    maximum stable gain elsewhere, or half the integrator's maximum stable gain; modes 3-120:
    half, modes 121-last: 0.4 of the leaky integrator's.  Starting points, not optima
    (`optimize gains` tunes them)."""
    g_tt = max_stable_gain(nominal_loop(observation, 0.1, True, structure))
    g_ho = max_stable_gain(nominal_loop(observation, 0.1, False, structure))
    if observation.tt_gain is not None:
        tt = observation.tt_gain
    else:
        tt = min(DEFAULT_IIR_TIP_TILT, 0.7 * g_tt) if observation.tt_control == "iir" else 0.5 * g_tt
    return LoopGains(round(tt, 3), round(0.5 * g_ho, 3), round(0.4 * g_ho, 3))


def design_gains(observation: LoopSettings, structure: StructuralResonance | None, gains: LoopGains | None = None) -> LoopGains:
    """The gains a run starts from: ``gains`` when given, else ``default_gains`` for the
    structural resonance as the frame rate samples it (``sampled_structure``: none above
    Nyquist), the one rule every run, optimisation and check uses."""
    return gains or default_gains(observation, sampled_structure(structure, observation.frame_rate_hz))


def _named_groups(observation: LoopSettings, gains: LoopGains) -> list[tuple[str, float, bool]]:
    """(name, gain, is Tip/Tilt) of each distinct gain to check."""
    if gains.modes is not None:
        first: dict[tuple[bool, float], int] = {}  # each distinct gain, named by the first mode that has it
        for i, g in enumerate(gains.modes):
            first.setdefault((i < TIP_TILT.stop, g), i + 1)
        return [("Tip/Tilt" if tt else f"mode {m}", g, tt) for (tt, g), m in first.items()]
    n = observation.modes  # the groups this observation has (modes 121-last only beyond 120)
    return [("Tip/Tilt", gains.tip_tilt, True)] + [
        (name, g, False)
        for name, g, first_mode in (
            (f"modes 3-{min(n, MID_GROUP_END)}", gains.mid, 3),
            (f"modes {MID_GROUP_END + 1}-last", gains.high, MID_GROUP_END + 1),
        )
        if n >= first_mode
    ]


def check_stability(observation: LoopSettings, gains: LoopGains, structure: StructuralResonance | None) -> None:
    """InputError naming the maximum stable gain if a group's gain is unstable for the nominal
    plant (chi = 1, the structural resonance on Tip/Tilt)."""
    for name, g, tt in _named_groups(observation, gains):
        if g <= 0:
            continue
        loop = nominal_loop(observation, g, tt, structure)
        if not loop.is_stable():
            raise InputError(
                f"{name} gain {g:g} is unstable at {observation.frame_rate_hz:g} Hz "
                f"(maximum stable gain {max_stable_gain(loop):.3f}); --allow-unstable runs it anyway"
            )


def unit_loops(observation: LoopSettings, structure, forgetting: float, n_modes: int) -> tuple[list[Filter], tuple | None]:
    """The unit-gain filters per mode and the (b, a) of the structural resonance on Tip/Tilt
    when the frame rate samples it (else None): the optimisers' plant without chi."""
    rate = observation.frame_rate_hz
    unit = mode_filters(observation, LoopGains(1.0, 1.0, 1.0, forgetting), n_modes)
    ba = sampled_coefficients(structure, rate)
    return unit, ba


def capped_gains(
    gains: np.ndarray, observation: LoopSettings, structure, chi: np.ndarray, forgetting: float, fraction: float
) -> np.ndarray:
    """``gains``, each capped at ``fraction`` of its maximum stable gain for a plant with
    optical gains chi_i (chi_i z^-d, the structure on Tip/Tilt)."""
    unit, ba = unit_loops(observation, structure, forgetting, len(chi))
    limits = gain_limits(unit, chi, observation.delay_frames, observation.frame_rate_hz, 0.0, ba)
    return np.minimum(gains, fraction * limits)


def read_gain_file(path: str | Path) -> np.ndarray:
    """The per-mode gains of a gain file (see the module); InputError naming the file and line."""
    p = Path(path)
    if p.suffix.lower() == ".toml":
        values = read_toml(p, "gain file").get("gains")
        if not isinstance(values, list) or not values:
            raise InputError(f"gain file {p} needs a list 'gains = [...]' with one gain per mode")
        gains = [_file_gain(v, p, f"gains[{i}]") for i, v in enumerate(values)]
    else:
        gains = _text_gains(read_input_text(p, "gain file"), p)
    return np.array(gains, dtype=float)


def gains_toml(gains: np.ndarray, comment: str) -> str:
    """A gain file `loop run --gains` reads: ``gains = [...]``, one per mode."""
    body = ",\n".join("  " + ", ".join(f"{g:.5f}" for g in gains[i : i + 8]) for i in range(0, len(gains), 8))
    lines = " ".join(comment.splitlines())
    return f"# {lines}\n# one gain per mode (mode 1 = Tip); use with: soulctl loop run --gains FILE\ngains = [\n{body},\n]\n"


def _file_gain(value, path: Path, where: str) -> float:
    if isinstance(value, str):
        try:
            value = float(value)
        except ValueError:
            raise InputError(f"gain file {path}, {where}: a gain must be a number in {LOOP_GAIN.text()}, got '{value}'") from None
    if not LOOP_GAIN.contains(value):
        raise InputError(f"gain file {path}, {where}: a gain must be a number in {LOOP_GAIN.text()}, got {number_text(value)}")
    return float(value)


def _text_gains(text: str, path: Path) -> list[float]:
    numbered = [(i + 1, line) for i, line in enumerate(text.splitlines()) if line.strip() and not line.lstrip().startswith("#")]
    if not numbered:
        raise InputError(f"gain file {path} holds no gains (one per line, or mode,gain lines)")
    rows = [(n, [c.strip() for c in row]) for (n, _), row in zip(numbered, csv.reader(line for _, line in numbered))]
    gain_column, mode_column = len(rows[0][1]) - 1, (0 if len(rows[0][1]) == 2 else None)
    if not _is_number(rows[0][1][-1]):
        gain_column, mode_column = _header(rows[0], path)
        rows = rows[1:]
    width = 1 + (mode_column is not None)
    gains, modes = [], []
    for n, row in rows:
        if len(row) != width:
            raise InputError(f"gain file {path}, line {n}: expected {'mode,gain' if width == 2 else 'one gain'}, got {row}")
        gains.append(_file_gain(row[gain_column], path, f"line {n}"))
        if mode_column is not None:
            modes.append(_mode(row[mode_column], path, n))
    return gains if not modes else _by_mode(gains, modes, path)


def _header(row: tuple[int, list[str]], path: Path) -> tuple[int, int | None]:
    """The (gain, mode) columns a header row names."""
    header = [c.lower() for c in row[1]]
    if "gain" not in header or set(header) - {"mode", "gain"}:
        raise InputError(f"gain file {path}, line {row[0]}: the header must name the columns mode,gain or gain, got {row[1]}")
    return header.index("gain"), (header.index("mode") if "mode" in header else None)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _mode(text: str, path: Path, line: int) -> int:
    try:
        return int(text)
    except ValueError:
        raise InputError(f"gain file {path}, line {line}: the mode must be an integer >= 1, got '{text}'") from None


def _by_mode(gains: list[float], modes: list[int], path: Path) -> list[float]:
    """Gains ordered by mode number; every mode 1..n exactly once."""
    if sorted(modes) != list(range(1, len(modes) + 1)):
        raise InputError(
            f"gain file {path}: the modes must be 1..{len(modes)}, each once (got {len(set(modes))} distinct, "
            f"from {min(modes)} to {max(modes)})"
        )
    out = [0.0] * len(gains)
    for m, g in zip(modes, gains):
        out[m - 1] = g
    return out
