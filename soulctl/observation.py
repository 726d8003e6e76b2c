"""An observation's configuration, set up from the magnitude look-up table (paper, Sec. 2.1:
"register the amount of detected flux ... and, based on this value, choose the configuration").

Frame-rate rule (where a table row gives a range): within a row the frame rate follows the
detected flux F as a power law, f = f_max (F / F_bright)^p, with p fixed by the row's own ends
(the row's brightest star gets f_max, its faintest f_min).  Since F = F0 10^(-0.4 R), this is
log f linear in R between the row's edges.  See docs/physics.md for the comparison with the
operating points quoted in the paper.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import tomli_w

from . import tables
from .control.delay import DelayModel
from .control.filters import Filter
from .control.transfer import check_stabilisable
from .errors import InputError
from .files import atomic_write_text, read_toml
from .optics.photometry import WfsPhotometry
from .ranges import DELAY_FRAMES, DESIGNED_GAIN, FRAME_RATE_HZ, MODES, MODULATION_LAMBDA_OVER_D, ROOT_MODULUS, ZERO_POINT_PH_S, number_text

TT_CONTROLS = ("iir", "int")
BINNINGS = {1: 40, 2: 20, 3: 13, 4: 10}  # binning -> sub-apertures across the pupil (paper, Tab. params)


def frame_rate(magnitude_r: float, band: tables.MagnitudeBand) -> float:
    """Frame rate (Hz, rounded to 1 Hz) for a star in a table row: the flux power law above."""
    f_max, f_min = band.frame_rate_max_hz, band.frame_rate_min_hz
    if f_max == f_min:
        return float(f_max)
    x = (magnitude_r - band.r_min) / (band.r_max - band.r_min)  # 0 at the bright edge, 1 at the faint
    x = min(max(x, 0.0), 1.0)
    return float(round(f_max * (f_min / f_max) ** x))


def tt_filter_roots(frame_rate_hz: float, roots: tuple[tables.IIRRoots, ...], where: str = "the roots table") -> tables.IIRRoots | None:
    """The Tip/Tilt IIR of the roots table at the tabulated rate nearest to ``frame_rate_hz``
    (ties to the higher rate; InputError if it is not within ``ranges.ROOTS_RATE_TOLERANCE``),
    or None below the table's lowest rate (750 Hz for the paper's) where an integrator is used."""
    if frame_rate_hz < min(r.frame_rate_hz for r in roots):
        return None
    return tables.nearest_roots(frame_rate_hz, roots, where)


def _require(cond: bool, message: str) -> None:
    if not cond:
        raise InputError(message)


def _is_number(value) -> bool:
    """A real number as TOML gives it: int or float, not bool."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _number(section: dict, key: str, where: str) -> float:
    value = section[key]
    _require(_is_number(value), f"{where}.{key} must be a number, got {value!r}")
    return float(value)


def _integer(section: dict, key: str, where: str) -> int:
    value = section[key]
    _require(isinstance(value, int) and not isinstance(value, bool), f"{where}.{key} must be an integer, got {value!r}")
    return value


def _numbers(section: dict, key: str, where: str) -> tuple[float, ...]:
    value = section.get(key, [])
    _require(isinstance(value, list) and all(_is_number(v) for v in value), f"{where}.{key} must be a list of numbers, got {value!r}")
    return tuple(float(v) for v in value)


def _section(d: dict, key: str, required: bool = True) -> dict:
    if key not in d and not required:
        return {}
    value = d[key]
    _require(isinstance(value, dict), f"[{key}] must be a table, got {value!r}")
    return value


@dataclass(frozen=True)
class Observation:
    """The free parameters of an observation (paper, Sec. 2.1) and the models that derive the rest."""

    magnitude_r: float
    binning: int
    modes: int
    frame_rate_hz: float
    modulation_lambda_over_d: float
    tt_control: str  # "iir" or "int"
    tt_filter_rate_hz: float | None = None  # rate of the roots-table row used, for provenance
    tt_zeros: tuple[float, ...] = ()
    tt_poles: tuple[float, ...] = ()
    tt_gain: float | None = None  # the IIR's designed gain (a designed roots table); None: the paper's 0.69 rule
    delay_model: DelayModel = field(default_factory=DelayModel.from_table)
    photometry: WfsPhotometry = field(default_factory=WfsPhotometry.from_table)

    def __post_init__(self):
        lo, hi = tables.magnitude_range(tables.magnitude_table())
        _require(
            _is_number(self.magnitude_r) and math.isfinite(self.magnitude_r) and lo <= self.magnitude_r <= hi,
            f"magnitude_r must be in the look-up table's {lo:g}..{hi:g}, got {number_text(self.magnitude_r)}",
        )
        _require(self.binning in BINNINGS, f"binning must be one of 1, 2, 3, 4, got {number_text(self.binning)}")
        MODES.check(self.modes, "modes")
        FRAME_RATE_HZ.check(self.frame_rate_hz, "frame_rate_hz")
        MODULATION_LAMBDA_OVER_D.check(self.modulation_lambda_over_d, "modulation_lambda_over_d")
        _require(self.tt_control in TT_CONTROLS, f"tt_control must be 'iir' or 'int', got '{self.tt_control}'")
        ZERO_POINT_PH_S.check(self.photometry.zero_point_ph_s, "photometry.zero_point_ph_s_per_subaperture")
        d = self.delay_frames
        _require(
            DELAY_FRAMES.contains(d),
            f"the loop delay ({self.delay_s * 1e3:.4g} ms = {d:.4g} frames at "
            f"{self.frame_rate_hz:g} Hz) must be at most {DELAY_FRAMES.hi:g} frames",
        )
        if self.tt_control == "iir":
            _require(
                len(self.tt_zeros) == 4 and len(self.tt_poles) == 4,
                "tt_control 'iir' needs 4 tt_zeros and 4 tt_poles",
            )
            _require(
                all(math.isfinite(z) and abs(z) <= ROOT_MODULUS for z in self.tt_zeros),
                f"tt_zeros must be in -{ROOT_MODULUS:g}..{ROOT_MODULUS:g}, got {list(self.tt_zeros)}",
            )
            _require(
                all(math.isfinite(p) and abs(p) <= 1.0 for p in self.tt_poles),
                f"tt_poles must be finite and in -1..1, got {list(self.tt_poles)}",
            )
            check_stabilisable(Filter.iir(self.tt_zeros, self.tt_poles, 1.0), d, self.frame_rate_hz, "the Tip/Tilt IIR filter")
        if self.tt_gain is not None:
            _require(self.tt_control == "iir", "tt_gain is the gain of a designed IIR: give it with tt_control 'iir'")
            DESIGNED_GAIN.check(self.tt_gain, "tt_gain")

    # Derived quantities: computed, never stored.
    @property
    def subapertures(self) -> int:
        """Sub-apertures across the pupil at this binning."""
        return BINNINGS[self.binning]

    @property
    def delay_s(self) -> float:
        return self.delay_model.total_s(self.frame_rate_hz)

    @property
    def delay_frames(self) -> float:
        return self.delay_model.frames(self.frame_rate_hz)

    @property
    def photons_per_subaperture_per_frame(self) -> float:
        return self.photometry.photons_per_frame(self.magnitude_r, self.binning, self.frame_rate_hz)

    def to_dict(self) -> dict:
        """A JSON/TOML-ready dict: free parameters by section, derived values under 'derived'."""
        d: dict[str, dict] = {
            "star": {"magnitude_r": self.magnitude_r},
            "wfs": {
                "binning": self.binning,
                "frame_rate_hz": self.frame_rate_hz,
                "modulation_lambda_over_d": self.modulation_lambda_over_d,
            },
            "control": {"modes": self.modes, "tt_control": self.tt_control},
            "delay": {
                "t_readout_ms": self.delay_model.t_readout_ms,
                "t_computation_ms": self.delay_model.t_computation_ms,
                "t_asm_ms": self.delay_model.t_asm_ms,
            },
            "photometry": {"zero_point_ph_s_per_subaperture": self.photometry.zero_point_ph_s},
            "derived": {
                "subapertures": self.subapertures,
                "delay_ms": round(self.delay_s * 1e3, 4),
                "delay_frames": round(self.delay_frames, 4),
                "photons_per_subaperture_per_frame": round(self.photons_per_subaperture_per_frame, 3),
            },
        }
        if self.tt_control == "iir":
            d["control"].update(
                tt_filter_rate_hz=self.tt_filter_rate_hz,
                tt_zeros=list(self.tt_zeros),
                tt_poles=list(self.tt_poles),
            )
            if self.tt_gain is not None:
                d["control"]["tt_gain"] = self.tt_gain
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Observation:
        """Inverse of to_dict; 'derived' is ignored and recomputed."""
        try:
            star, wfs, control = _section(d, "star"), _section(d, "wfs"), _section(d, "control")
            delay, phot_section = _section(d, "delay", required=False), _section(d, "photometry", required=False)
            default = DelayModel.from_table()
            terms = {
                key: _number(delay, key, "delay") if key in delay else getattr(default, key)
                for key in ("t_readout_ms", "t_computation_ms", "t_asm_ms")
            }
            # the tables' provenance is kept where a file repeats their values
            same = all(terms[k] == getattr(default, k) for k in terms)
            delay_model = DelayModel(**terms, source=default.source if same else "configuration file")
            phot = WfsPhotometry.from_table()
            if "zero_point_ph_s_per_subaperture" in phot_section:
                zp = _number(phot_section, "zero_point_ph_s_per_subaperture", "photometry")
                if zp != phot.zero_point_ph_s:
                    phot = WfsPhotometry(zp, phot.reference_subapertures, phot.pupil_diameter_m, "configuration file")
            tt_control = control["tt_control"]
            _require(isinstance(tt_control, str), f"control.tt_control must be 'iir' or 'int', got {tt_control!r}")
            rate = control.get("tt_filter_rate_hz")
            return cls(
                magnitude_r=_number(star, "magnitude_r", "star"),
                binning=_integer(wfs, "binning", "wfs"),
                modes=_integer(control, "modes", "control"),
                frame_rate_hz=_number(wfs, "frame_rate_hz", "wfs"),
                modulation_lambda_over_d=_number(wfs, "modulation_lambda_over_d", "wfs"),
                tt_control=tt_control,
                tt_filter_rate_hz=_number(control, "tt_filter_rate_hz", "control") if rate is not None else None,
                tt_zeros=_numbers(control, "tt_zeros", "control"),
                tt_poles=_numbers(control, "tt_poles", "control"),
                tt_gain=_number(control, "tt_gain", "control") if "tt_gain" in control else None,
                delay_model=delay_model,
                photometry=phot,
            )
        except KeyError as e:
            raise InputError(f"configuration is missing the key {e.args[0]!r}") from None

    def to_toml(self) -> str:
        header = (
            "# soulctl observation configuration (soulctl configure --out).\n"
            "# [derived] is informational: it is recomputed from the other sections when read.\n"
        )
        return header + tomli_w.dumps(self.to_dict())

    def write_toml(self, path: str | Path) -> None:
        """Write the TOML file atomically (temporary file, then rename)."""
        atomic_write_text(Path(path), self.to_toml())

    @classmethod
    def read_toml(cls, path: str | Path) -> Observation:
        """The observation of a configuration file; InputError naming the file and the field."""
        data = read_toml(path, "configuration file")
        try:
            return cls.from_dict(data)
        except InputError as e:
            raise InputError(f"configuration file {path}: {e}") from None


def observation_for_magnitude(
    magnitude_r: float, roots_table: tuple[tables.IIRRoots, ...] | None = None, roots_source: str | None = None
) -> Observation:
    """The configuration the look-up table gives for a guide star of R magnitude; the Tip/Tilt
    filter from ``roots_table`` (default: the paper's, tables/tt_iir_roots.csv; ``roots_source``
    names a user's table in messages)."""
    bands = tables.magnitude_table()
    band = tables.band_for_magnitude(magnitude_r, bands)
    rate = frame_rate(magnitude_r, band)
    roots = tt_filter_roots(
        rate, roots_table or tables.tt_iir_table(), f"roots table {roots_source}" if roots_source else "the roots table"
    )
    return Observation(
        magnitude_r=float(magnitude_r),
        binning=band.binning,
        modes=band.modes,
        frame_rate_hz=rate,
        modulation_lambda_over_d=band.modulation_lambda_over_d,
        tt_control="iir" if roots else "int",
        tt_filter_rate_hz=roots.frame_rate_hz if roots else None,
        tt_zeros=roots.zeros if roots else (),
        tt_poles=roots.poles if roots else (),
        tt_gain=roots.gain if roots else None,
    )
