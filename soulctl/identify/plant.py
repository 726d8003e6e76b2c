"""The identified plant: the plant file `telemetry identify --out` writes (``plant.toml``) and
`filter design|analyze --plant`, `loop run --plant` and `rtc check --plant` read.

    source = "telemetry file ..."      # where the figures come from
    rate_hz = 1700.0
    [delay]          frames, sigma, method
    [optical_gain]   method; [[optical_gain.group]] first_mode, last_mode, chi, sigma
    [noise]          tip_tilt_mas (per axis, RMS per frame), modes_nm2 = [...] (per mode,
                     measurement noise of R s / k, nm^2 per frame; Tip/Tilt in nm^2 too)
    [turbulence]     seeing_arcsec, seeing_sigma, r0_m, L0_m, L0_sigma, wind_m_s (or absent)
    [vibrations]     source, [[vibrations.line]] frequency_hz, damping, tip_mas, tilt_mas, note
                     (the format of --vibrations files; per-line uncertainties in the note)
    [controller]     tip_tilt_zeros, tip_tilt_poles (numbers, or [re, im] for complex roots),
                     tip_tilt_gain: the Tip/Tilt filter the record ran, its gain times the slope
                     sensitivity k (the loop's gain is that x chi)

Every section but delay may be absent when the record did not allow the estimate; the reader
names what a command needs and is missing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..control.design import Disturbance
from ..control.filters import Filter
from ..disturbance.turbulence import TurbulenceTipTilt
from ..disturbance.vibrations import VibrationSpectrum
from ..errors import InputError
from ..files import read_toml
from ..ranges import DELAY_FRAMES, FRAME_RATE_HZ, OUTER_SCALE_M, SEEING_ARCSEC, WIND_M_S


@dataclass(frozen=True)
class Estimate:
    """An identified figure and its 1-sigma uncertainty (inf: the data do not constrain it)."""

    value: float
    sigma: float

    def to_dict(self) -> dict:
        return {"value": self.value, "sigma": self.sigma if math.isfinite(self.sigma) else None}


@dataclass(frozen=True)
class OpticalGainGroup:
    first_mode: int  # 1-based
    last_mode: int
    chi: float
    sigma: float


@dataclass(frozen=True)
class Turbulence:
    seeing_arcsec: float
    seeing_sigma: float
    L0_m: float
    L0_sigma: float
    wind_m_s: float | None = None


def chi_per_mode(groups: tuple[OpticalGainGroup, ...], n_modes: int) -> np.ndarray:
    """chi_i per mode: each group's value, the nearest group's beyond them, 1 without any."""
    out = np.ones(n_modes)
    for i in range(n_modes if groups else 0):
        mode = i + 1
        out[i] = min(
            groups, key=lambda g: 0 if g.first_mode <= mode <= g.last_mode else min(abs(mode - g.first_mode), abs(mode - g.last_mode))
        ).chi
    return out


@dataclass(frozen=True)
class PlantModel:
    """What `telemetry identify` found (see the module)."""

    source: str
    rate_hz: float
    delay: Estimate
    delay_method: str = ""
    optical_gains: tuple[OpticalGainGroup, ...] = ()
    optical_gain_method: str = ""
    noise_nm2: np.ndarray | None = None
    tip_tilt_noise_mas: float | None = None
    turbulence: Turbulence | None = None
    vibrations: VibrationSpectrum | None = None
    notes: tuple[str, ...] = field(default=())
    tip_tilt_filter: Filter | None = None  # the Tip/Tilt controller the record ran, its gain g k (k: the slope sensitivity)

    def chi(self, n_modes: int) -> np.ndarray:
        return chi_per_mode(self.optical_gains, n_modes)

    def to_toml(self) -> str:
        lines = [f"source = {_text(self.source)}", f"rate_hz = {_num(self.rate_hz)}", ""]
        lines += [
            "[delay]",
            f"frames = {_num(self.delay.value)}",
            f"sigma = {_num(self.delay.sigma)}",
            f"method = {_text(self.delay_method)}",
            "",
        ]
        if self.optical_gains:
            lines += ["[optical_gain]", f"method = {_text(self.optical_gain_method)}", ""]
            for g in self.optical_gains:
                lines += ["[[optical_gain.group]]", f"first_mode = {g.first_mode}", f"last_mode = {g.last_mode}"]
                lines += [f"chi = {_num(g.chi)}", f"sigma = {_num(g.sigma)}", ""]
        if self.noise_nm2 is not None:
            lines += ["[noise]", f"tip_tilt_mas = {_num(self.tip_tilt_noise_mas)}"]
            lines += ["modes_nm2 = [" + ", ".join(_num(x) for x in self.noise_nm2) + "]", ""]
        if self.turbulence is not None:
            t = self.turbulence
            lines += ["[turbulence]", f"seeing_arcsec = {_num(t.seeing_arcsec)}", f"seeing_sigma = {_num(t.seeing_sigma)}"]
            lines += [f"L0_m = {_num(t.L0_m)}", f"L0_sigma = {_num(t.L0_sigma)}"]
            lines += [f"wind_m_s = {_num(t.wind_m_s)}"] if t.wind_m_s is not None else []
            lines.append("")
        if self.vibrations is not None:
            lines += ["[vibrations]", f"source = {_text(self.vibrations.source)}", ""]
            for v in self.vibrations.lines:
                lines += ["[[vibrations.line]]", f"frequency_hz = {_num(v.frequency_hz)}", f"damping = {_num(v.damping)}"]
                lines += [f"tip_mas = {_num(v.tip_mas)}", f"tilt_mas = {_num(v.tilt_mas)}", f"note = {_text(v.note)}", ""]
        if self.tip_tilt_filter is not None:
            h = self.tip_tilt_filter
            lines += ["[controller]", "tip_tilt_zeros = [" + ", ".join(_root(z) for z in h.zeros) + "]"]
            lines += ["tip_tilt_poles = [" + ", ".join(_root(p) for p in h.poles) + "]", f"tip_tilt_gain = {_num(h.gain)}", ""]
        if self.notes:
            lines += ["notes = [" + ", ".join(_text(n) for n in self.notes) + "]"]
        return "\n".join(_front(lines)) + "\n"

    def vibrations_toml(self) -> str:
        """The vibration lines alone, as a --vibrations file."""
        if self.vibrations is None:
            raise InputError("the plant holds no vibration lines")
        out = [f"source = {_text(self.vibrations.source)}", ""]
        for v in self.vibrations.lines:
            out += ["[[line]]", f"frequency_hz = {_num(v.frequency_hz)}", f"damping = {_num(v.damping)}", f"tip_mas = {_num(v.tip_mas)}"]
            out += [f"tilt_mas = {_num(v.tilt_mas)}", f"note = {_text(v.note)}", ""]
        return "\n".join(out)


def _front(lines: list[str]) -> list[str]:
    """Top-level keys (notes) must come before the first table in TOML."""
    notes = [x for x in lines if x.startswith("notes = ")]
    rest = [x for x in lines if not x.startswith("notes = ")]
    return notes + rest


def _text(s: str) -> str:
    return '"' + str(s).replace("\\", "\\\\").replace('"', '\\"').replace("\n", " ") + '"'


def _root(r: complex) -> str:
    """A zero or pole: a number when real, [re, im] when complex (a recorded filter's)."""
    r = complex(r)
    return _num(r.real) if r.imag == 0 else f"[{_num(r.real)}, {_num(r.imag)}]"


def _num(x: float | None) -> str:
    if x is None or not math.isfinite(float(x)):
        return "inf" if x is not None and float(x) == math.inf else "nan"
    return repr(float(x))


def _number(data: dict, key: str, where: str, default: object = InputError) -> float:
    v = data.get(key, default)
    if v is InputError:
        raise InputError(f"{where}: missing {key}")
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        raise InputError(f"{where}: {key} must be a number, got {_num(v)}")
    return float(v)


def read_plant(path: str | Path) -> PlantModel:
    """A plant file (see the module); InputError naming the key that is wrong."""
    data = read_toml(path, "plant file")
    where = f"plant file {path}"
    unknown = sorted(set(data) - {"source", "rate_hz", "delay", "optical_gain", "noise", "turbulence", "vibrations", "notes", "controller"})
    if unknown:
        raise InputError(f"{where}: unknown key {', '.join(unknown)}")
    rate = FRAME_RATE_HZ.check(_number(data, "rate_hz", where), f"{where}: rate_hz")
    d = data.get("delay")
    if not isinstance(d, dict):
        raise InputError(f"{where}: needs a [delay] table with frames")
    delay = Estimate(
        DELAY_FRAMES.check(_number(d, "frames", where + " [delay]"), f"{where}: delay.frames"), _number(d, "sigma", where, math.inf)
    )
    groups = tuple(
        _group(g, f"{where} optical_gain.group {i + 1}") for i, g in enumerate(_tables(data.get("optical_gain", {}), "group", where))
    )
    noise = data.get("noise")
    modes_nm2 = None
    tt_noise = None
    if isinstance(noise, dict):
        values = noise.get("modes_nm2")
        if values is not None:
            arr = (
                np.asarray(values, dtype=float)
                if isinstance(values, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
                else None
            )
            if arr is None or arr.ndim != 1:
                raise InputError(f"{where}: noise.modes_nm2 must be a list of numbers")
            modes_nm2 = arr
        tt = noise.get("tip_tilt_mas")
        tt_noise = float(tt) if isinstance(tt, (int, float)) and not isinstance(tt, bool) and math.isfinite(tt) and tt >= 0 else None
    turbulence = _turbulence(data.get("turbulence"), where) if "turbulence" in data else None
    vib = data.get("vibrations")
    vibrations = None
    if vib is not None:
        if not isinstance(vib, dict):
            raise InputError(f"{where}: [vibrations] must be a table")
        vibrations = VibrationSpectrum.from_dict(vib, f"{where} [vibrations]")
    return PlantModel(
        str(data.get("source", path)), rate, delay, str(d.get("method", "")), groups, "", modes_nm2, tt_noise, turbulence, vibrations,
        tip_tilt_filter=_controller(data.get("controller"), where),
    )  # fmt: skip


def _controller(c: object, where: str) -> Filter | None:
    """The [controller] Tip/Tilt filter (real zeros and poles, the gain), None without one."""
    if c is None:
        return None
    if not isinstance(c, dict) or set(c) != {"tip_tilt_zeros", "tip_tilt_poles", "tip_tilt_gain"}:
        raise InputError(f"{where}: [controller] holds tip_tilt_zeros, tip_tilt_poles and tip_tilt_gain")
    roots = [c["tip_tilt_zeros"], c["tip_tilt_poles"]]
    if not all(isinstance(r, list) and all(_is_root(x) for x in r) for r in roots):
        raise InputError(f"{where}: controller.tip_tilt_zeros and tip_tilt_poles must be lists of numbers or [re, im] pairs")
    zeros, poles = (tuple(complex(*x) if isinstance(x, list) else float(x) for x in r) for r in roots)
    return Filter.iir(zeros, poles, _number(c, "tip_tilt_gain", where))


def _is_root(x: object) -> bool:
    """A finite real number, or a [re, im] pair of them."""
    parts = x if isinstance(x, list) and len(x) == 2 else [x]
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in parts)


def _tables(section: object, key: str, where: str) -> list:
    if not isinstance(section, dict):
        raise InputError(f"{where}: [{key}] must be a table")
    items = section.get(key, [])
    if not isinstance(items, list) or not all(isinstance(x, dict) for x in items):
        raise InputError(f"{where}: {key} must be an array of tables")
    return items


def _group(g: dict, where: str) -> OpticalGainGroup:
    lo, hi = int(_number(g, "first_mode", where)), int(_number(g, "last_mode", where))
    chi = _number(g, "chi", where)
    if not (1 <= lo <= hi) or not (0 < chi < 100):
        raise InputError(f"{where}: needs 1 <= first_mode <= last_mode and chi in (0, 100), got {lo}, {hi}, {chi:g}")
    return OpticalGainGroup(lo, hi, chi, _number(g, "sigma", where, math.inf))


def _turbulence(t: object, where: str) -> Turbulence:
    if not isinstance(t, dict):
        raise InputError(f"{where}: [turbulence] must be a table")
    seeing = SEEING_ARCSEC.check(_number(t, "seeing_arcsec", where), f"{where}: turbulence.seeing_arcsec")
    L0 = OUTER_SCALE_M.check(_number(t, "L0_m", where), f"{where}: turbulence.L0_m")
    wind = t.get("wind_m_s")
    if wind is not None:
        wind = WIND_M_S.check(_number(t, "wind_m_s", where), f"{where}: turbulence.wind_m_s")
    return Turbulence(seeing, _number(t, "seeing_sigma", where, math.inf), L0, _number(t, "L0_sigma", where, math.inf), wind)


def plant_disturbance(plant: PlantModel, wind_m_s: float, resonance_mas: float) -> Disturbance:
    """The Tip/Tilt disturbance of `filter design` for an identified plant: von Karman
    Tip/Tilt at its seeing and L0 (the wind given, or the plant's), its vibration lines (none
    when it found none) and its Tip/Tilt noise referred to the wavefront."""
    missing = [name for name, v in (("[turbulence]", plant.turbulence), ("noise.tip_tilt_mas", plant.tip_tilt_noise_mas)) if v is None]
    if missing:
        raise InputError(f"plant file {plant.source}: filter design needs {' and '.join(missing)}")
    t = plant.turbulence
    assert t is not None and plant.tip_tilt_noise_mas is not None
    turbulence = TurbulenceTipTilt(t.seeing_arcsec, t.L0_m, t.wind_m_s if t.wind_m_s is not None else wind_m_s)
    vibrations = plant.vibrations or VibrationSpectrum((), "no vibration line identified")
    return Disturbance(turbulence, vibrations, min(plant.tip_tilt_noise_mas, 1e4 - 1), resonance_mas=resonance_mas)


def plant_overrides(plant: PlantModel) -> dict:
    """The run description's fields of a simulated twin of the plant (`loop run --plant`):
    frame rate, total delay, seeing, L0 (and wind) and the vibration lines (none if it found none)."""
    out: dict = {"wfs.frame_rate_hz": plant.rate_hz, "delay.frames": plant.delay.value}
    if plant.turbulence is not None:
        t = plant.turbulence
        out |= {"atmosphere.seeing_arcsec": t.seeing_arcsec, "atmosphere.L0_m": t.L0_m}
        if t.wind_m_s is not None:
            out["atmosphere.wind_m_s"] = t.wind_m_s
    if plant.vibrations is None:
        return out | {"vibrations.enabled": False}
    lines = [
        {"frequency_hz": x.frequency_hz, "damping": x.damping, "tip_mas": x.tip_mas, "tilt_mas": x.tilt_mas, "note": x.note}
        for x in plant.vibrations.lines
    ]
    return out | {"vibrations.line": lines, "vibrations.source": plant.vibrations.source}
