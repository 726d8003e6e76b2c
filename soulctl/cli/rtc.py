"""``soulctl rtc check``: the check before a parameter set goes to the real RTC."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import typer

from ..control.check import DEFAULT_MODULUS_MARGIN, STATE_BUDGET, Criteria, check_modes, state_count
from ..control.coupling import CouplingStability, registration_verdict
from ..control.gains import LoopGains, mode_filters, read_gain_file
from ..control.rtc_file import TOLERANCE, compare, is_rtc_file, read_rtc_file
from ..control.structure import sampled_structure
from ..errors import InputError
from ..files import input_file
from ..identify.plant import read_plant
from ..loop.run import calibration_for, loop_calibration
from ..offline.recorded import checked_rate
from ..optics.cache import ArrayCache
from ..optics.calibration import moved_mirror_response
from ..optics.optical_gains import read_optical_gain_table
from ..ranges import WFS_FIELD_OF_VIEW_ARCSEC, Range
from .common import (
    CACHE_DIR,
    JSON_OUTPUT,
    MISREGISTRATION,
    NO_CACHE,
    RUN_CONFIG,
    WFS_FIELD,
    array_cache,
    misregistration_overrides,
    quantity_table,
    run_description,
)
from .numbers import magnitude_option, number
from .option_table import command
from .output import console as make_console
from .output import print_json

app = typer.Typer(no_args_is_help=True, help="Real-time computer parameter sets: the checks before an upload.")

UNSAFE_EXIT = 3
MARGIN = Range(0.0, 1.0)
GAIN_MARGIN = Range(1.0, 1e6)
PHASE_MARGIN = Range(0.0, 180.0, "deg")
WORST = 10  # modes in the table


@dataclass(frozen=True)
class CheckOptions:
    params: Path = typer.Argument(
        ..., metavar="GAINS", help="Per-mode gains: a gain file as 'optimize gains --out' writes it (TOML, CSV or text)."
    )
    config: Path | None = RUN_CONFIG
    mag: str | None = magnitude_option()
    plant: Path | None = typer.Option(None, "--plant", metavar="PLANT.toml", help="Identified plant: its delay and optical gains chi_i.")
    chi_table: Path | None = typer.Option(
        None, "--chi-table", metavar="FILE.csv", help="Optical gains per mode ('optics gains --out'), instead of the plant's."
    )
    modulus_margin: float = typer.Option(
        DEFAULT_MODULUS_MARGIN, "--modulus-margin", parser=number(MARGIN), help="Least min|1 + L| per mode (0..1; the paper's epsilon 0.2)."
    )
    gain_margin: float = typer.Option(1.0, "--gain-margin", parser=number(GAIN_MARGIN), help="Least gain margin per mode (1: stable).")
    phase_margin: float = typer.Option(0.0, "--phase-margin", parser=number(PHASE_MARGIN), help="Least phase margin per mode (deg).")
    misregistration: str | None = MISREGISTRATION
    wfs_field: float | None = WFS_FIELD
    no_cache: bool = NO_CACHE
    cache_dir: Path | None = CACHE_DIR
    json_output: bool = JSON_OUTPUT


@app.command("check")
@command(CheckOptions)
def check_cmd(o: CheckOptions) -> int:
    """Check per-mode gains or a whole RTC description before an upload.

    The check covers each mode's
    stability, gain, phase and modulus margins and maximum stable gain on the plant (delay,
    optical gain chi_i, the 127 Hz structure on Tip/Tilt), the RTC states against the 672-state
    budget, and for an RTC description Lambda, Delta, Xi, Sigma rebuilt from the declared
    filters (--config/--mag) and compared.  With a mis-registration (--misregistration, or the
    [misregistration] of --config) also the coupled loop of the moved mirror: its eigenmodes'
    stability and common gain margin (the modelled R D', calibrated on the pyramid of
    --wfs-field, else --config's field, else SOUL's).  Exit 0 when all holds, 3 when a mode
    or eigenmode is unstable or below a margin or the matrices differ, 2 on malformed input.

    Example: soulctl rtc check gains.toml --plant plant.toml --mag 13
    """
    _check_options(o)
    field = {} if o.wfs_field is None else {"run.wfs_field_arcsec": o.wfs_field}
    description = run_description(o.config, o.mag, misregistration_overrides(o.misregistration) | field)
    obs = description.observation
    comparison = None
    if is_rtc_file(o.params):
        unit = mode_filters(obs, LoopGains(1.0, 1.0, 1.0, description.controller.forgetting), obs.modes)
        comparison = compare(read_rtc_file(o.params), unit)
        gains = comparison.gains
    else:
        gains = read_gain_file(o.params)
    if len(gains) != obs.modes:
        raise InputError(f"PARAMS {o.params} holds {len(gains)} gains; the configuration controls {obs.modes} modes (--config/--mag)")
    chi, delay = _plant(o, obs)
    filters = mode_filters(obs, LoopGains.from_modes(gains, description.controller.forgetting), obs.modes)
    structure = sampled_structure(description.structure, obs.frame_rate_hz)
    ba = None if structure is None else structure.coefficients(obs.frame_rate_hz)
    criteria = Criteria(o.modulus_margin, o.gain_margin, o.phase_margin)
    checks = check_modes(filters, chi, delay, obs.frame_rate_hz, ba, criteria)
    states = state_count(filters)
    coupling = _coupling(description, np.asarray(gains) * chi, delay, array_cache(o.no_cache, o.cache_dir))
    coupled = coupling is None or (coupling.stable and coupling.margin >= criteria.gain_margin)
    ok = all(c.passed for c in checks) and states <= STATE_BUDGET and (comparison is None or comparison.consistent) and coupled
    if o.json_output:
        print_json(
            {
                "passed": ok,
                "states": states,
                "state_budget": STATE_BUDGET,
                "delay_frames": delay,
                "rate_hz": obs.frame_rate_hz,
                "criteria": criteria.__dict__,
                "failed_modes": [c.mode for c in checks if not c.passed],
                "rebuild_differences": None if comparison is None else comparison.differences,
                "misregistration_stability": None if coupling is None else coupling.to_dict() | {"passed": coupled},
                "modes": [c.to_dict() for c in checks],
            }
        )
    else:
        _render(checks, states, delay, ok, comparison, coupling, criteria)
    return 0 if ok else UNSAFE_EXIT


def _check_options(o: CheckOptions) -> None:
    """InputError naming the option and its accepted range, or the missing PARAMS file."""
    for value, option, accepted in (
        (o.modulus_margin, "--modulus-margin", MARGIN),
        (o.gain_margin, "--gain-margin", GAIN_MARGIN),
        (o.phase_margin, "--phase-margin", PHASE_MARGIN),
        (o.wfs_field, "--wfs-field", WFS_FIELD_OF_VIEW_ARCSEC),
    ):
        if value is not None:
            accepted.check(value, option)
    input_file(o.params, "PARAMS")


def _plant(o: CheckOptions, obs) -> tuple[np.ndarray, float]:
    """(chi_i, delay in frames) of the check: the identified plant's (--plant), chi from
    --chi-table when given; without either chi = 1 and the configuration's delay."""
    plant = read_plant(o.plant) if o.plant is not None else None
    if plant is not None:  # a plant identified from a record whose rate was measured: within the records' tolerance
        checked_rate(plant.rate_hz, obs.frame_rate_hz, f"--plant {o.plant}", "the plant")
    chi = np.ones(obs.modes) if plant is None else plant.chi(obs.modes)
    if o.chi_table is not None:
        chi = read_optical_gain_table(o.chi_table, obs.modes)
    return chi, (plant.delay.value if plant is not None else obs.delay_frames)


def _coupling(description, gains_chi: np.ndarray, delay: float, cache: ArrayCache) -> CouplingStability | None:
    """The coupled loop with the description's mis-registration (``control.coupling``): Q = R D',
    R the reconstructor `loop run` would hold (the modelled calibration, measured with the
    description's [calibration] noise when it has some), D' the moved mirror's response, and
    the gains times the check's chi_i; None when the mirror is registered."""
    registration = description.misregistration
    if registration.is_identity:
        return None
    request = description.request()
    cal = calibration_for(request, cache)
    q = loop_calibration(request, cal).reconstructor @ moved_mirror_response(cal, registration, cache)
    obs = description.observation
    return registration_verdict(obs, description.structure, description.controller.forgetting, q, gains_chi, delay)


def _render(checks, states: int, delay: float, ok: bool, comparison, coupling: CouplingStability | None, criteria: Criteria) -> None:
    worst = sorted(checks, key=lambda c: (c.passed, c.modulus_margin))[:WORST]
    t = quantity_table(f"worst modes by modulus margin (delay {delay:.3f} frames)")
    for c in worst:
        pm = "-" if c.phase_margin_deg is None else f"{c.phase_margin_deg:.0f} deg"
        verdict = "ok" if c.passed else ("UNSTABLE" if not c.stable else "below a margin")
        t.add_row(
            f"mode {c.mode}: g {c.gain:.3g}, chi {c.chi:.3g}",
            f"GM {c.gain_margin:.2f}, PM {pm}, min|1+L| {c.modulus_margin:.3f}, g_max {c.max_stable_gain:.3g}: {verdict}",
        )
    t.add_row("RTC states", f"{states} of {STATE_BUDGET}")
    if comparison is not None:
        for name, d in comparison.differences.items():
            t.add_row(
                f"{name} against the declared filters",
                "not compared (no R, M)" if d is None else f"{d:.2e} ({'ok' if d <= TOLERANCE else 'DIFFERS'})",
            )
    lost = ""
    if coupling is not None:
        t.add_row("mis-registration: unstable eigenmodes", coupling.figures_text())
        if not coupling.stable:
            lost = f"; mis-registered, {coupling.unstable_text()}"
        elif coupling.margin < criteria.gain_margin:
            lost = f"; mis-registered, gain margin x{coupling.margin:.2f} below --gain-margin {criteria.gain_margin:g}"
    failed = sum(not c.passed for c in checks)
    t.add_row(
        "verdict",
        "safe to upload" if ok else f"NOT safe: {failed} mode(s) fail" + ("" if states <= STATE_BUDGET else ", too many states") + lost,
    )
    make_console().print(t)
