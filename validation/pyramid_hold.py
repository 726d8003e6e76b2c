"""Can the pyramid hold a loop that a linear sensor has closed?  The R9.7 loop (1700 Hz, 40x40,
500 modes, default gains, no NCPA, k = 1, seed 1) runs its first --linear-s seconds on a linear
wavefront sensor (slopes = D0 times the true residual's modes: the calibration's interaction
matrix, optical gain 1, no noise), then on the modelled pyramid with its detector for the rest.
If the loop at 1.6" falls from the linear sensor's residual to the one it reaches when closed
on the pyramid from a flat mirror, the pyramid cannot hold it, whatever the closing procedure.

    python -m validation.pyramid_hold [--seeings 1.0,1.6] [--linear-s 0.3] [--duration 1.5]
        [--wavelengths 750] [--oversampling 2] [--field-stop 0] [--twin GAIN] [--out FILE]

Residual RMS (nm, all pupil pixels) over spans before and after the switch, with the Marechal
H-band Strehl ratio exp(-(2 pi sigma / 1650 nm)^2) as a rough scale; "og" rows divide every
gain by its mode's optical gain at that seeing (``loop.chi_model.optical_gain_table``) at the
switch.  ``--wavelengths`` runs the pyramid (and its calibration) monochromatic at other
wavelengths of SOUL's 600-950 nm band, or on a band of several (``658+775+892``), the
modulation kept at the same angle (3 lambda/D at 750 nm): whether the band, whose red end
sees the same OPD as less phase, holds the 1.6" loop the 750 nm model loses.  ``--twin G``
runs the loop of ``oopao_hold.py`` (the same experiment in OOPAO): pure integrators of gain G,
no error terms, no noise, no vibrations.  ~40 s per row on one core.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from soulctl.cli.common import default_cache_dir
from soulctl.cli.loop import IDEAL
from soulctl.files import atomic_write_text
from soulctl.loop.chi_model import optical_gain_table
from soulctl.loop.run import calibration_for, calibration_setup, closed_loop_for
from soulctl.optics.cache import ArrayCache
from soulctl.optics.calibration import calibrate
from soulctl.optics.pwfs import WFS_WAVELENGTH_M
from soulctl.run_config import RunConfig
from validation.provenance import provenance

OUT = Path(__file__).parent / "results" / "pyramid_hold.json"
H_NM = 1650.0


def linear_until(loop, calibration, frames: int) -> None:
    """Replace the loop's pyramid by a linear sensor (D0 times the residual's modes) for its
    first ``frames`` frames: the residual map is read where the pyramid receives it."""
    sensor, d0 = loop.sensor, calibration.interaction_matrix.astype(np.float32)
    intensity, slopes_of_frame, seen = sensor.pyramid.intensity, sensor.slopes_of_frame, {}

    def pyramid(opd):
        seen["opd"] = opd
        return intensity(opd)

    def slopes(frame):
        if loop.frame >= frames:
            return slopes_of_frame(frame)
        return (d0 @ loop.mirror.project(seen["opd"][loop.pupil.mask].astype(np.float64))).astype(np.float32)

    sensor.pyramid.intensity, sensor.slopes_of_frame = pyramid, slopes


def calibration_at(request, wavelengths_nm: tuple[float, ...], cache: ArrayCache, field_stop: float = 0.0):
    """The request's calibration with the pyramid at ``wavelengths_nm`` (one: monochromatic;
    several: a band of equal photon weights, ``PyramidConfig.band_nm``), the modulation at the
    same angle as the default's (3 lambda/D at 750 nm), and a field stop of radius
    ``field_stop`` lambda/D at 750 nm (0: none)."""
    if wavelengths_nm == (WFS_WAVELENGTH_M * 1e9,) and field_stop == 0:
        return calibration_for(request, cache)
    setup = calibration_setup(request)
    pyramid = dataclasses.replace(setup.pyramid, field_stop_lambda_over_d=field_stop)
    if len(wavelengths_nm) == 1:
        pyramid = pyramid.monochromatic(wavelengths_nm[0])
    else:
        pyramid = dataclasses.replace(pyramid, band_nm=wavelengths_nm)
    return calibrate(dataclasses.replace(setup, pyramid=pyramid), cache)


def spans(rms: np.ndarray, switch: int) -> dict:
    """Residual RMS (nm) and the Marechal H-band Strehl ratio over the spans around the switch
    to the pyramid at frame ``switch`` (``rms``: one residual per frame); also the OOPAO twin's."""
    n = len(rms)
    edges = {"linear, last 200 frames": (switch - 200, switch), "pyramid, first 200": (switch, switch + 200)}
    edges |= {"pyramid, next 600": (switch + 200, switch + 800), "pyramid, last 500": (n - 500, n)}
    out = {}
    for name, (a, b) in edges.items():
        sigma = float(np.sqrt(np.mean(rms[a:b] ** 2)))
        out[name] = {"frames": [a, b], "residual_nm": sigma, "marechal_h": float(np.exp(-((2 * np.pi * sigma / H_NM) ** 2)))}
    return out


def twin_values(gain: float) -> dict:
    """The loop ``oopao_hold.py`` runs in OOPAO: every mode on a pure integrator of ``gain``, and
    none of soulctl's error terms (``loop run --ideal``'s settings, no detector noise, no
    vibrations, no structural resonance)."""
    values = {"control.tt_control": "int", "control.gains": [gain] * 3, "control.forgetting": 1.0}
    return values | IDEAL | {"detector.noise": False, "vibrations.enabled": False, "structure.enabled": False}


def one(
    seeing: float,
    linear_s: float,
    duration: float,
    og: bool,
    cache: ArrayCache,
    wavelengths_nm=(750.0,),
    oversampling=2,
    stop=0.0,
    twin=0.0,
):
    values = {"star.magnitude_r": 9.7, "run.band": "H", "ncpa.rms_nm": 0.0, "atmosphere.seeing_arcsec": seeing, "run.seed": 1}
    values |= {"run.oversampling": oversampling}
    if twin > 0:
        values |= twin_values(twin)
    request = RunConfig().with_values(values | {"run.duration_s": duration}).request()
    obs = request.observation
    cal = calibration_at(request, wavelengths_nm, cache, stop)
    structure = request.sampled_structure()
    gains = request.design_gains()
    loop = closed_loop_for(request, cal, gains, structure)
    switch, n = round(linear_s * obs.frame_rate_hz), round(duration * obs.frame_rate_hz)
    linear_until(loop, cal, switch)
    rms = np.zeros(n)
    for k in range(n):
        if k == switch and og:
            loop.set_gains(gains.per_mode(obs.modes) / optical_gain_table(cal, cache, seeing))
        rms[k] = np.sqrt(np.mean(loop.step() ** 2))
    described = {"seeing": seeing, "wavelengths_nm": list(wavelengths_nm), "oversampling": oversampling}
    described |= {"field_stop_lambda_over_d": stop, "og_compensated_at_switch": og, "twin_gain": twin or None}
    return described | {"linear_s": linear_s, "duration_s": duration, "spans": spans(rms, switch)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeings", default="1.0,1.6")
    p.add_argument("--linear-s", type=float, default=0.3)
    p.add_argument("--duration", type=float, default=1.5)
    p.add_argument("--wavelengths", default="750", help="nm, comma-separated; a band as 658+775+892")
    p.add_argument("--oversampling", type=int, default=2, help="simulation pixels per binning-1 detector pixel (pupil 40 o px)")
    p.add_argument("--field-stop", type=float, default=0.0, help="field stop radius, lambda/D at 750 nm (SOUL's 2.1\" field: 56)")
    p.add_argument("--og", choices=("both", "no"), default="both", help='also the rows with gains / gamma_i above 1.0"')
    p.add_argument("--twin", type=float, default=0.0, help="the loop of validation/oopao_hold.py at this integrator gain (0: the defaults)")
    p.add_argument("--out", type=Path, default=OUT)
    a = p.parse_args()
    cache = ArrayCache(default_cache_dir())
    rows = []
    bands = [tuple(float(w) for w in band.split("+")) for band in a.wavelengths.split(",")]
    for seeing, nm in ((float(s), band) for s in a.seeings.split(",") for band in bands):
        for og in (False, True) if seeing > 1.0 and a.og == "both" else (False,):
            row = one(seeing, a.linear_s, a.duration, og, cache, nm, a.oversampling, a.field_stop, a.twin) | provenance()
            print(json.dumps(row), flush=True)
            rows.append(row)
    atomic_write_text(a.out, json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
