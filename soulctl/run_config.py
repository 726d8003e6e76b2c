"""The run description: one declarative, complete record of a simulated closed loop, read and
written as TOML without loss, validated in one place, and the one factory of the loop's
requests (``RunConfig.request``).

Its TOML form extends the observation file of `soulctl configure --out` (which stays a valid
run description); every section and key is optional, and what a file leaves out takes the
look-up table's value for its star, else ``soulctl.defaults``:

    [star]        magnitude_r                       the look-up table's row for this magnitude ...
    [wfs]         binning, frame_rate_hz,           ... overridden key by key; a binning without
                  modulation_lambda_over_d           modes takes the table's modes, a frame rate
    [control]     modes, tt_control, tt_zeros,       without roots the Tip/Tilt IIR of the nearest
                  tt_poles, tt_filter_rate_hz,       tabulated rate (an integrator below 750 Hz)
                  tt_gain (a designed IIR's gain, the Tip/Tilt default when gains are not given),
                  gains (TT, 3-120, 121-last) or mode_gains (one per mode), forgetting,
                  allow_unstable
    [delay]       t_readout_ms, t_computation_ms, t_asm_ms, or frames (the total, explicitly)
    [photometry]  zero_point_ph_s_per_subaperture
    [atmosphere]  seeing_arcsec (or r0_m at 500 nm), L0_m, wind_m_s (the LBT profile's
                  effective speed), or [[atmosphere.layer]]: altitude_m, fraction,
                  wind_speed_m_s, wind_direction_deg
    [vibrations]  enabled, file, scale, [[vibrations.line]] (the format of --vibrations files)
    [structure]   enabled, frequency_hz, damping, coupling (the 127 Hz resonance)
    [misregistration]  shift_x_pitch, shift_y_pitch, rotation_deg, magnification (the mirror
                  on the pyramid against the calibration; ``optics.registration``)
    [ncpa]        rms_nm, exponent, compensated, seed, offset_fraction (the science path's static
                  aberration and its reference-slope offsets; ``optics.ncpa``; default 100 nm,
                  LUCI1's, with half its offsets when OGTL runs: ``defaults.NCPA_RMS_NM``,
                  ``defaults.NCPA_OFFSET_FRACTION``)
    [calibration] photons_per_frame, frames, seed, seeing_arcsec (the interaction matrix measured
                  at a finite flux, 0 photons: noiseless; around the residual of a seeing, 0: none;
                  ``optics.calibration_noise``)
    [mirror]      influence ("thin-plate", the default, or "gaussian": ``optics.asm``)
    [detector]    noise
    [auxiliary]   mgm, ogtl, period_s, probe_mode, probe_amplitude_nm, probe_frequency_hz
    [run]         duration_s, band, seed, oversampling, wfs_field_arcsec (the pyramid's simulated
                  field, a diameter; 2.1, the default: SOUL's, with a stop at its edge; 0: the
                  field the pupil's sampling gives, +-0.75" at oversampling 2, with no stop, ~2x
                  cheaper; ``optics.pwfs.PyramidConfig.field_of_view_arcsec``.  A description
                  soulctl wrote (``HEADER``, or stored in telemetry) without the key predates
                  this default and ran 0; one written by hand takes the default)

``to_toml`` writes the description resolved (the observation whole, the vibration lines inline,
the gains the run starts from), so that a stored description re-runs the same loop.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import tomli_w

from . import defaults, tables
from .control.gains import DEFAULT_FORGETTING, LoopGains, design_gains
from .control.ogtl import PROBE_MODE, OgtlSettings
from .control.structure import StructuralResonance
from .disturbance.vibrations import LINE_KEYS, VibrationLine, VibrationSpectrum
from .errors import InputError
from .loop.metrics import BANDS
from .loop.optimisers import LiveOptimisers
from .loop.run import RunRequest
from .observation import Observation, observation_for_magnitude, tt_filter_roots
from .optics.asm import DEFAULT_INFLUENCE, check_influence
from .optics.atmosphere import Layer, r0_from_seeing
from .optics.calibration_noise import CalibrationNoise
from .optics.ncpa import NcpaSpec
from .optics.registration import Misregistration
from .ranges import (
    DURATION_S,
    LOOP_GAIN,
    OUTER_SCALE_M,
    OVERSAMPLING,
    PERIOD_S,
    SEED,
    SEEING_ARCSEC,
    WFS_FIELD_OF_VIEW_ARCSEC,
    WIND_M_S,
    Range,
)

HEADER = "# soulctl run description (soulctl loop run --print-config; read by loop run --config).\n"
OBSERVATION_SECTIONS = ("star", "wfs", "control", "delay", "photometry")
CONTROLLER_KEYS = ("gains", "mode_gains", "forgetting", "allow_unstable")
REGISTRATION_KEYS = ("shift_x_pitch", "shift_y_pitch", "rotation_deg", "magnification")
KEYS: dict[str, tuple[str, ...] | None] = {
    "star": ("magnitude_r",),
    "wfs": ("binning", "frame_rate_hz", "modulation_lambda_over_d"),
    "control": ("modes", "tt_control", "tt_filter_rate_hz", "tt_zeros", "tt_poles", "tt_gain", *CONTROLLER_KEYS),
    "delay": ("t_readout_ms", "t_computation_ms", "t_asm_ms", "frames"),
    "photometry": ("zero_point_ph_s_per_subaperture",),
    "derived": None,  # informational, recomputed
    "atmosphere": ("seeing_arcsec", "r0_m", "L0_m", "wind_m_s", "layer"),
    "vibrations": ("enabled", "file", "scale", "source", "line"),
    "structure": ("enabled", "frequency_hz", "damping", "coupling"),
    "misregistration": REGISTRATION_KEYS,
    "ncpa": ("rms_nm", "exponent", "compensated", "seed", "offset_fraction"),
    "calibration": ("photons_per_frame", "frames", "seed", "seeing_arcsec"),
    "mirror": ("influence",),
    "detector": ("noise",),
    "auxiliary": ("mgm", "ogtl", "period_s", "probe_mode", "probe_amplitude_nm", "probe_frequency_hz"),
    "run": ("duration_s", "band", "seed", "oversampling", "wfs_field_arcsec"),
}
# What an override makes stale (re-derived unless given too); "section.*": the section's keys
# but the controller's.
_TT_FILTER = ("control.tt_control", "control.tt_zeros", "control.tt_poles", "control.tt_filter_rate_hz", "control.tt_gain")
STALE = {
    "star.magnitude_r": (*(f"{s}.*" for s in OBSERVATION_SECTIONS), "control.mode_gains"),
    "wfs.binning": ("control.modes", "control.mode_gains"),
    "control.modes": ("control.mode_gains",),
    "wfs.frame_rate_hz": _TT_FILTER,
    "control.gains": ("control.mode_gains",),
    "control.mode_gains": ("control.gains",),
    "vibrations.file": tuple(f"vibrations.{k}" for k in ("line", "source", "scale")),
    "vibrations.enabled": tuple(f"vibrations.{k}" for k in ("line", "source", "scale")),
    "vibrations.line": ("vibrations.file", "vibrations.enabled"),
    "delay.frames": tuple(f"delay.{k}" for k in ("t_readout_ms", "t_computation_ms", "t_asm_ms")),
}
LAYER_KEYS = ("altitude_m", "fraction", "wind_speed_m_s", "wind_direction_deg")
FORGETTING = Range(0.0, 1.0)
VIBRATION_SCALE = Range(0.0, 100.0)


@dataclass(frozen=True, kw_only=True)
class AtmosphereSpec:
    """Seeing and outer scale; the LBT profile at ``wind_m_s``, or explicit ``layers``."""

    seeing_arcsec: float = defaults.SEEING_ARCSEC
    L0_m: float = defaults.L0_M
    wind_m_s: float = defaults.WIND_M_S
    layers: tuple[Layer, ...] = ()

    def __post_init__(self):
        SEEING_ARCSEC.check(self.seeing_arcsec, "atmosphere.seeing_arcsec")
        OUTER_SCALE_M.check(self.L0_m, "atmosphere.L0_m")
        WIND_M_S.check(self.wind_m_s, "atmosphere.wind_m_s")


@dataclass(frozen=True, kw_only=True)
class ControllerSpec:
    """The modal gains: ``gains`` the paper's three groups (Tip/Tilt, modes 3-120, 121-last) or
    ``mode_gains`` one per mode (neither: ``control.gains.design_gains``), and the leaky
    integrators' forgetting factor (1: pure integrators)."""

    gains: tuple[float, ...] = ()
    mode_gains: tuple[float, ...] = ()
    forgetting: float = DEFAULT_FORGETTING
    allow_unstable: bool = False

    def __post_init__(self):
        FORGETTING.check(self.forgetting, "control.forgetting")
        if self.gains and self.mode_gains:
            raise InputError("[control] takes gains (the three groups) or mode_gains (one per mode), not both")
        if len(self.gains) not in (0, 3):
            raise InputError(f"control.gains needs 3 values (Tip/Tilt, modes 3-120, 121-last), got {len(self.gains)}")
        for g in self.gains + self.mode_gains:
            LOOP_GAIN.check(g, "control.gains" if self.gains else "control.mode_gains")

    def loop_gains(self) -> LoopGains | None:
        if self.mode_gains:
            return LoopGains.from_modes(self.mode_gains, self.forgetting)
        if not self.gains:
            return None
        tip_tilt, mid, high = self.gains
        return LoopGains(tip_tilt, mid, high, forgetting=self.forgetting)


@dataclass(frozen=True, kw_only=True)
class AuxiliarySpec:
    """`loop run --mgm --ogtl`: the auxiliary loops beside the run (None: the operating point's
    default).  ``ogtl`` None: on when the run is long enough for OGTL to act (the loop closes,
    then two updates), as SOUL runs it on sky; ``RunConfig.resolved`` decides."""

    mgm: bool = False
    ogtl: bool | None = None
    period_s: float | None = None
    probe_mode: int = PROBE_MODE
    probe_amplitude_nm: float | None = None
    probe_frequency_hz: float | None = None

    def __post_init__(self):
        if self.period_s is not None:
            PERIOD_S.check(self.period_s, "auxiliary.period_s")
        self.probe()  # checks the probe's fields

    def probe(self) -> OgtlSettings:
        return OgtlSettings(self.probe_mode, self.probe_amplitude_nm, self.probe_frequency_hz)

    def live(self) -> LiveOptimisers | None:
        """The auxiliary loops of `loop run --mgm/--ogtl` (None: neither; OGTL's automatic
        default counts as off until resolved)."""
        if not (self.mgm or self.ogtl):
            return None
        return LiveOptimisers(self.mgm, bool(self.ogtl), self.period_s, self.probe())

    def resolved(self, observation, duration_s: float) -> AuxiliarySpec:
        """``ogtl`` decided: on when the run lasts long enough for the loop to close and OGTL
        to update twice (``LiveOptimisers.frames_needed``), else off."""
        if self.ogtl is not None:
            return self
        need = LiveOptimisers(False, True, self.period_s, self.probe()).frames_needed(observation)
        return dataclasses.replace(self, ogtl=round(duration_s * observation.frame_rate_hz) >= need)


@dataclass(frozen=True, kw_only=True)
class RunConfig:
    """A whole simulated run (see the module for its TOML form: each field is a section).

    Parameters
    ----------
    observation : Observation
        [star], [wfs], [control] (modes, Tip/Tilt filter), [delay], [photometry].
    atmosphere : AtmosphereSpec
        [atmosphere]: seeing, L0, wind or explicit layers.
    vibrations : VibrationSpectrum or None
        [vibrations]: the Tip/Tilt lines; None: none.
    structure : StructuralResonance or None
        [structure]: the 127 Hz resonance; None: none.
    misregistration : Misregistration
        [misregistration]: the mirror on the pyramid against the calibration.
    ncpa : NcpaSpec
        [ncpa]: the science path's static aberration and its offsets.
    calibration : CalibrationNoise
        [calibration]: the interaction matrix's flux and correction level.
    noise : bool
        [detector] noise.
    influence : str
        [mirror] influence: the influence-function model.
    controller : ControllerSpec
        [control]: gains (per group or per mode), forgetting, allow_unstable.
    auxiliary : AuxiliarySpec
        [auxiliary]: MGM, OGTL, their period and probe.
    duration_s : float
        [run] simulated time (s).
    band : str
        [run] science band of the Strehl ratio.
    seed : int
        [run] seed of every random draw.
    oversampling : int
        [run] simulation pixels per binning-1 detector pixel.
    wfs_field_arcsec : float
        [run] the pyramid's simulated field (a diameter, arcsec); 0: as sampled, no stop.
    """

    observation: Observation = field(default_factory=lambda: observation_for_magnitude(defaults.MAGNITUDE_R))
    atmosphere: AtmosphereSpec = AtmosphereSpec()
    vibrations: VibrationSpectrum | None = field(default_factory=VibrationSpectrum.lbt_default)
    structure: StructuralResonance | None = StructuralResonance()
    misregistration: Misregistration = Misregistration()
    ncpa: NcpaSpec = NcpaSpec(rms_nm=defaults.NCPA_RMS_NM, compensated=None)  # sky-like; None: offsets with OGTL
    calibration: CalibrationNoise = CalibrationNoise()
    noise: bool = True
    influence: str = DEFAULT_INFLUENCE  # the mirror's influence-function model
    controller: ControllerSpec = ControllerSpec()
    auxiliary: AuxiliarySpec = AuxiliarySpec()
    duration_s: float = defaults.DURATION_S
    band: str = defaults.BAND
    seed: int = defaults.SEED
    oversampling: int = defaults.OVERSAMPLING
    wfs_field_arcsec: float = defaults.WFS_FIELD_ARCSEC  # the pyramid's simulated field; 0: as sampled, no stop

    def __post_init__(self):
        DURATION_S.check(self.duration_s, "run.duration_s")
        WFS_FIELD_OF_VIEW_ARCSEC.check(self.wfs_field_arcsec, "run.wfs_field_arcsec")
        SEED.check(self.seed, "run.seed")
        OVERSAMPLING.check(self.oversampling, "run.oversampling")
        check_influence(self.influence)
        if self.band not in BANDS:
            raise InputError(f"run.band must be one of {', '.join(BANDS)}, got {self.band!r}")
        n = len(self.controller.mode_gains)
        if n not in (0, self.observation.modes):
            raise InputError(f"control.mode_gains has {n} gains but {self.observation.modes} modes are controlled")

    def request(self, ogtl: bool | None = None) -> RunRequest:
        """The run's request: the one place a ``RunRequest`` is built from a description.  NCPA
        offsets left automatic (``ncpa.compensated`` None) follow OGTL: ``ogtl`` where the
        caller runs its own (`optimize gains`), else the description's resolved decision."""
        a, resolved = self.atmosphere, self.resolved()
        ncpa = resolved.ncpa
        if ncpa.compensated is None:
            ncpa = dataclasses.replace(ncpa, compensated=bool(resolved.auxiliary.ogtl if ogtl is None else ogtl))
        return RunRequest(
            observation=self.observation,
            seeing_arcsec=a.seeing_arcsec,
            wind_m_s=a.wind_m_s,
            L0_m=a.L0_m,
            duration_s=self.duration_s,
            gains=resolved.controller.loop_gains(),
            band=self.band,
            seed=self.seed,
            noise=self.noise,
            vibrations=self.vibrations,
            oversampling=self.oversampling,
            structure=self.structure,
            allow_unstable=self.controller.allow_unstable,
            layers=a.layers or None,
            misregistration=None if self.misregistration.is_identity else self.misregistration,
            ncpa=ncpa if ncpa.active else None,
            calibration_noise=self.calibration if self.calibration.active else None,
            influence=self.influence,
            wfs_field_arcsec=self.wfs_field_arcsec,
        )

    def resolved(self) -> RunConfig:
        """The description with the gains the run starts from written out (the defaults'
        today) and OGTL's automatic default decided, so that the stored description does not
        depend on tomorrow's defaults."""
        aux = self.auxiliary.resolved(self.observation, self.duration_s)
        if self.controller.gains or self.controller.mode_gains:
            return dataclasses.replace(self, auxiliary=aux)
        g = design_gains(self.observation, self.structure)
        return dataclasses.replace(
            self,
            controller=dataclasses.replace(self.controller, gains=(float(g.tip_tilt), float(g.mid), float(g.high))),
            auxiliary=aux,
        )

    def to_dict(self) -> dict:
        return _to_dict(self)

    def to_toml(self) -> str:
        return HEADER + tomli_w.dumps(self.to_dict())

    @classmethod
    def from_dict(cls, data: dict, where: str = "run description") -> RunConfig:
        try:
            return _from_dict(data)
        except InputError as e:
            raise InputError(f"{where}: {e}") from None

    def with_values(self, values: dict) -> RunConfig:
        """The description with dotted fields replaced (``{"atmosphere.seeing_arcsec": 0.8}``),
        checked as a file's would be.  What a field derives from is re-derived unless given too
        (``STALE``): ``star.magnitude_r`` takes the table's observation for that magnitude (the
        controller's keys stay), ``wfs.binning`` the table's modes, ``wfs.frame_rate_hz`` the
        Tip/Tilt filter of that rate."""
        for dotted in values:
            section, _, key = dotted.partition(".")
            if key not in (KEYS.get(section) or ()):
                raise InputError(f"unknown run description field {dotted!r}")
        d = self.to_dict()
        d.pop("derived", None)
        for dotted in values:
            for stale in STALE.get(dotted, ()):
                section, _, key = stale.partition(".")
                if stale in values:
                    continue
                if key == "*":
                    d[section] = {k: v for k, v in d.get(section, {}).items() if section == "control" and k in CONTROLLER_KEYS}
                else:
                    d.get(section, {}).pop(key, None)
        for dotted, value in values.items():
            section, _, key = dotted.partition(".")
            d.setdefault(section, {})[key] = value
        return RunConfig.from_dict(d, "the run description with its overrides")


def read_run_config(path: str | Path) -> RunConfig:
    """A run description from a TOML file, or the one stored in telemetry (.h5, AOT .fits or
    an LBT folder written by soulctl)."""
    path = Path(path)
    if path.suffix.lower() in (".h5", ".hdf5", ".fits", ".fit", ".fts") or path.is_dir():
        from .telemetry.formats import stored_run_description

        return RunConfig.from_dict(stored(stored_run_description(path)), f"telemetry file {path}")
    from .files import parse_toml, read_input_text

    text = read_input_text(path, "run description")
    data = parse_toml(text, path, "run description")
    return RunConfig.from_dict(stored(data) if text.startswith(HEADER) else data, f"run description {path}")


def stored(description: dict) -> dict:
    """A description soulctl stored (resolved, every key written: ``to_toml``'s file or a
    telemetry file's) as it ran: without ``[run] wfs_field_arcsec`` it predates SOUL's field as
    the default and ran ``defaults.PREDATED_WFS_FIELD_ARCSEC``."""
    run = description.setdefault("run", {})
    if isinstance(run, dict):
        run.setdefault("wfs_field_arcsec", defaults.PREDATED_WFS_FIELD_ARCSEC)
    return description


# ---- the TOML form -------------------------------------------------------------------------


def _to_dict(c: RunConfig) -> dict:
    d = c.observation.to_dict()
    ctl = c.controller
    d["control"].update({"forgetting": ctl.forgetting, "allow_unstable": ctl.allow_unstable})
    for key in ("gains", "mode_gains"):
        if getattr(ctl, key):
            d["control"][key] = list(getattr(ctl, key))
    a = c.atmosphere
    d["atmosphere"] = {"seeing_arcsec": a.seeing_arcsec, "L0_m": a.L0_m, "wind_m_s": a.wind_m_s}
    if a.layers:
        d["atmosphere"]["layer"] = [
            {
                "altitude_m": x.altitude_m,
                "fraction": x.weight,
                "wind_speed_m_s": x.wind_speed_m_s,
                "wind_direction_deg": x.wind_direction_deg,
            }
            for x in a.layers
        ]
    v = c.vibrations
    d["vibrations"] = {"enabled": False} if v is None else {"enabled": True, "source": v.source, "line": [_line(x) for x in v.lines]}
    s = c.structure
    d["structure"] = {"enabled": False} if s is None else {"enabled": True, **dataclasses.asdict(s)}
    d["misregistration"] = dataclasses.asdict(c.misregistration)
    d["ncpa"] = {k: v for k, v in dataclasses.asdict(c.ncpa).items() if v is not None}
    d["calibration"] = dataclasses.asdict(c.calibration)
    d["mirror"] = {"influence": c.influence}
    d["detector"] = {"noise": c.noise}
    d["auxiliary"] = {k: v for k, v in dataclasses.asdict(c.auxiliary).items() if v is not None}
    d["run"] = {"duration_s": c.duration_s, "band": c.band, "seed": c.seed, "oversampling": c.oversampling}
    d["run"]["wfs_field_arcsec"] = c.wfs_field_arcsec
    return d


def _line(x: VibrationLine) -> dict:
    return {k: getattr(x, k) for k in LINE_KEYS} | ({"note": x.note} if x.note else {})


def _check_keys(data: dict) -> None:
    unknown = sorted(set(data) - set(KEYS))
    if unknown:
        raise InputError(f"unknown section [{unknown[0]}] (accepted: {', '.join(k for k in KEYS if k != 'derived')})")
    for section, value in data.items():
        if not isinstance(value, dict):
            raise InputError(f"[{section}] must be a table, got {value!r}")
        accepted = KEYS[section]
        if accepted is None:
            continue
        extra = sorted(set(value) - set(accepted))
        if extra:
            raise InputError(f"[{section}] has the unknown key {extra[0]!r} (accepted: {', '.join(accepted)})")


def _from_dict(data: dict) -> RunConfig:
    _check_keys(data)
    ctl = data.get("control", {})
    aux = data.get("auxiliary", {})
    run = data.get("run", {})
    try:
        return RunConfig(
            observation=_observation(data),
            atmosphere=_atmosphere(data.get("atmosphere", {})),
            vibrations=_vibrations(data.get("vibrations", {})),
            structure=_structure(data.get("structure", {})),
            misregistration=Misregistration(**{k: _number(v, f"misregistration.{k}") for k, v in data.get("misregistration", {}).items()}),
            ncpa=_ncpa(data.get("ncpa", {})),
            calibration=_calibration(data.get("calibration", {})),
            noise=_bool(data.get("detector", {}), "noise", True, "detector"),
            influence=str(data.get("mirror", {}).get("influence", DEFAULT_INFLUENCE)),
            controller=ControllerSpec(
                gains=tuple(_numbers(ctl.get("gains", []), "control.gains")),
                mode_gains=tuple(_numbers(ctl.get("mode_gains", []), "control.mode_gains")),
                forgetting=_number(ctl.get("forgetting", DEFAULT_FORGETTING), "control.forgetting"),
                allow_unstable=_bool(ctl, "allow_unstable", False, "control"),
            ),
            auxiliary=AuxiliarySpec(
                mgm=_bool(aux, "mgm", False, "auxiliary"),
                ogtl=_bool(aux, "ogtl", True, "auxiliary") if "ogtl" in aux else None,
                **{k: _number(aux[k], f"auxiliary.{k}") for k in ("period_s", "probe_amplitude_nm", "probe_frequency_hz") if k in aux},
                probe_mode=_integer(aux.get("probe_mode", PROBE_MODE), "auxiliary.probe_mode"),
            ),
            duration_s=_number(run.get("duration_s", defaults.DURATION_S), "run.duration_s"),
            band=str(run.get("band", defaults.BAND)),
            seed=_integer(run.get("seed", defaults.SEED), "run.seed"),
            oversampling=_integer(run.get("oversampling", defaults.OVERSAMPLING), "run.oversampling"),
            wfs_field_arcsec=_number(run.get("wfs_field_arcsec", defaults.WFS_FIELD_ARCSEC), "run.wfs_field_arcsec"),
        )
    except TypeError as e:  # a value of the wrong kind deep in a constructor
        raise InputError(str(e)) from None


def _observation(data: dict) -> Observation:
    """The table's observation for the star, overridden key by key (see the module)."""
    star = data.get("star", {})
    mag = _number(star.get("magnitude_r", defaults.MAGNITUDE_R), "star.magnitude_r")
    lo, hi = tables.magnitude_range(tables.magnitude_table())
    if not lo <= mag <= hi:
        raise InputError(f"star.magnitude_r must be in the look-up table's {lo:g}..{hi:g}, got {mag:g}")
    base = observation_for_magnitude(mag).to_dict()
    given = {s: dict(data.get(s, {})) for s in OBSERVATION_SECTIONS}
    wfs, ctl = given["wfs"], given["control"]
    if "binning" in wfs and "modes" not in ctl:
        rows = [b for b in tables.magnitude_table() if b.binning == wfs["binning"]]
        if rows:
            ctl["modes"] = rows[0].modes
    if "frame_rate_hz" in wfs and "tt_zeros" not in ctl and ctl.get("tt_control") != "int":
        roots = tt_filter_roots(_number(wfs["frame_rate_hz"], "wfs.frame_rate_hz"), tables.tt_iir_table())
        ctl.setdefault("tt_control", "iir" if roots else "int")
        base["control"].update(
            {"tt_filter_rate_hz": roots.frame_rate_hz, "tt_zeros": list(roots.zeros), "tt_poles": list(roots.poles)} if roots else {}
        )
    merged = {s: {**base.get(s, {}), **given[s]} for s in OBSERVATION_SECTIONS}
    merged["control"] = {k: v for k, v in merged["control"].items() if k not in CONTROLLER_KEYS}
    c = merged["control"]
    if c.get("tt_control") == "int":
        for k in ("tt_zeros", "tt_poles", "tt_filter_rate_hz", "tt_gain"):
            c.pop(k, None)
    elif c.get("tt_control") == "iir" and not c.get("tt_zeros"):
        raise InputError(f"control.tt_control 'iir': the roots table has no IIR filter at {merged['wfs']['frame_rate_hz']:g} Hz")
    if "frames" in given["delay"]:
        merged["delay"] = _explicit_delay(given["delay"], merged["wfs"]["frame_rate_hz"])
    return Observation.from_dict(merged)


def _explicit_delay(delay: dict, rate_hz) -> dict:
    """A total delay of ``frames`` frames as the delay model's terms: one frame of integration
    plus a computation term (the model's other terms 0)."""
    if set(delay) != {"frames"}:
        others = sorted(set(delay) - {"frames"})
        raise InputError(f"[delay] frames is the total delay: give it without {', '.join(others)}")
    frames = _number(delay["frames"], "delay.frames")
    rate = _number(rate_hz, "wfs.frame_rate_hz")
    if not (1.0 <= frames <= 10.0):
        raise InputError(f"delay.frames must be in 1..10 (one frame of integration at least), got {frames:g}")
    return {"t_readout_ms": 0.0, "t_computation_ms": (frames - 1.0) / rate * 1e3, "t_asm_ms": 0.0}


def _ncpa(n: dict) -> NcpaSpec:
    return NcpaSpec(
        rms_nm=_number(n.get("rms_nm", defaults.NCPA_RMS_NM), "ncpa.rms_nm"),
        exponent=_number(n.get("exponent", 2.0), "ncpa.exponent"),
        compensated=_bool(n, "compensated", False, "ncpa") if "compensated" in n else None,
        seed=_integer(n.get("seed", 1), "ncpa.seed"),
        offset_fraction=_number(n.get("offset_fraction", defaults.NCPA_OFFSET_FRACTION), "ncpa.offset_fraction"),
    )


def _calibration(c: dict) -> CalibrationNoise:
    return CalibrationNoise(
        photons_per_frame=_number(c.get("photons_per_frame", 0.0), "calibration.photons_per_frame"),
        frames=_integer(c.get("frames", 1), "calibration.frames"),
        seed=_integer(c.get("seed", 1), "calibration.seed"),
        seeing_arcsec=_number(c.get("seeing_arcsec", 0.0), "calibration.seeing_arcsec"),
    )


def _atmosphere(a: dict) -> AtmosphereSpec:
    if "r0_m" in a and "seeing_arcsec" in a:
        raise InputError("[atmosphere] takes seeing_arcsec or r0_m, not both")
    seeing = _number(a.get("seeing_arcsec", defaults.SEEING_ARCSEC), "atmosphere.seeing_arcsec")
    if "r0_m" in a:
        r0 = _number(a["r0_m"], "atmosphere.r0_m")
        if not r0 > 0:
            raise InputError(f"atmosphere.r0_m must be > 0 m, got {r0:g}")
        seeing = r0_from_seeing(1.0) / r0  # r0 is inversely proportional to the seeing
    layers = a.get("layer", [])
    if not isinstance(layers, list):
        raise InputError("atmosphere.layer must be an array of tables ([[atmosphere.layer]])")
    return AtmosphereSpec(
        seeing_arcsec=seeing,
        L0_m=_number(a.get("L0_m", defaults.L0_M), "atmosphere.L0_m"),
        wind_m_s=_number(a.get("wind_m_s", defaults.WIND_M_S), "atmosphere.wind_m_s"),
        layers=tuple(_layer(x, i) for i, x in enumerate(layers)),
    )


def _layer(x, i: int) -> Layer:
    where = f"atmosphere.layer {i + 1}"
    if not isinstance(x, dict) or set(x) - set(LAYER_KEYS):
        raise InputError(f"{where} must be a table with {', '.join(LAYER_KEYS)}")
    return Layer(
        altitude_m=_number(x.get("altitude_m", 0.0), where),
        weight=_number(x.get("fraction", 1.0), where),
        wind_speed_m_s=_number(x.get("wind_speed_m_s", defaults.WIND_M_S), where),
        wind_direction_deg=_number(x.get("wind_direction_deg", 0.0), where),
    )


def _vibrations(v: dict) -> VibrationSpectrum | None:
    if not _bool(v, "enabled", True, "vibrations"):
        return None
    if "file" in v and "line" in v:
        raise InputError("[vibrations] takes a file or [[vibrations.line]] tables, not both")
    if "file" in v:
        spectrum = VibrationSpectrum.read(str(v["file"]))
    elif "line" in v:
        spectrum = VibrationSpectrum.from_dict({k: v[k] for k in ("line", "source") if k in v}, "[vibrations]")
    else:
        spectrum = VibrationSpectrum.lbt_default()
    scale = VIBRATION_SCALE.check(_number(v.get("scale", 1.0), "vibrations.scale"), "vibrations.scale")
    if scale == 1.0:
        return spectrum
    lines = tuple(dataclasses.replace(x, tip_mas=x.tip_mas * scale, tilt_mas=x.tilt_mas * scale) for x in spectrum.lines)
    return VibrationSpectrum(lines, f"{spectrum.source} x {scale:g}")


def _structure(s: dict) -> StructuralResonance | None:
    if not _bool(s, "enabled", True, "structure"):
        return None
    return StructuralResonance(**{k: _number(s[k], f"structure.{k}") for k in ("frequency_hz", "damping", "coupling") if k in s})


def _bool(d: dict, key: str, default: bool, section: str) -> bool:
    value = d.get(key, default)
    if not isinstance(value, bool):
        raise InputError(f"{section}.{key} must be true or false, got {value!r}")
    return value


def _number(value, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"{name} must be a finite number, got {value!r}")
    return float(value)


def _integer(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise InputError(f"{name} must be an integer, got {value!r}")
    return value


def _numbers(values, name: str) -> list[float]:
    if not isinstance(values, list):
        raise InputError(f"{name} must be an array of numbers, got {values!r}")
    return [_number(v, name) for v in values]
