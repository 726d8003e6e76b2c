"""The pyramid-hold experiment (``pyramid_hold.py``) in an independent simulator, OOPAO: does
another implementation of the modulated pyramid also lose, at poor seeing, a loop that a
linear sensor has closed?  If it does, the loss belongs to the modelled configuration (the
paper's table: 40x40, 3 lambda/D, monochromatic 750 nm), not to soulctl's code.

The twin takes from soulctl what defines the run: the LBT pupil (8.222 m, obstruction 0.111),
the WFS wavelength (750 nm, OOPAO's band "I2"), the four-layer Mt. Graham profile scaled to
v_eff = 8 m/s, L0 = 25 m, the seeing at 500 nm on the line of sight, 1700 Hz and the loop delay
of R9.7 (3.567 frames, applied as soulctl's delay line does: (1 - e) c(k - n) + e c(k - n - 1)).
OOPAO brings its own parts: a 41x41 Cartesian mirror (1344 valid actuators, Gaussian influence
functions, coupling 0.35) and its KL basis (the first 500 modes), its pyramid (40
sub-apertures on an 80-pixel pupil, 20 modulation points, a +-40 lambda/D focal field like
soulctl's), slopes normalised by the incident flux, and its own phase screens (with
subharmonics).  Every mode runs on a pure integrator of one gain (``pyramid_hold.py --twin
GAIN`` runs soulctl alike, with every error term off).

The first ``--linear`` frames close the loop on a linear sensor (the least-squares
projection of the true residual on the controlled modes: optical gain 1, no aliasing, no
noise); then the pyramid takes over.  Residual RMS (nm, over the pupil) over the same spans
as ``pyramid_hold.py`` and the Marechal H-band Strehl ratio.

Not in CI (OOPAO is not a dependency of soulctl): install it apart, e.g.

    python -m venv --system-site-packages /tmp/oopao && /tmp/oopao/bin/pip install ".[oopao]"
    /tmp/oopao/bin/python -m validation.oopao_hold [--seeings 1.0,1.2,1.4,1.6] [--gain 0.25]
        [--frames 2550] [--linear 510] [--out FILE]

~3 min per seeing on one core after a 30 s calibration.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from OOPAO.Atmosphere import Atmosphere
from OOPAO.calibration.compute_KL_modal_basis import compute_KL_basis
from OOPAO.calibration.InteractionMatrix import InteractionMatrix
from OOPAO.DeformableMirror import DeformableMirror
from OOPAO.Pyramid import Pyramid
from OOPAO.Source import Source
from OOPAO.Telescope import Telescope

from soulctl.control.delay import fractional_taps
from soulctl.files import atomic_write_text
from soulctl.observation import observation_for_magnitude
from soulctl.optics.atmosphere import AtmosphereConfig
from soulctl.optics.pupil import LBT_DIAMETER_M, LBT_OBSTRUCTION
from soulctl.optics.pwfs import SUBAPERTURES_BIN1, WFS_WAVELENGTH_M, PyramidConfig
from validation.provenance import provenance
from validation.pyramid_hold import spans  # the same spans and Strehl scale as soulctl's run (this folder)

OUT = Path(__file__).parent / "results" / "pyramid_hold_oopao.json"
PYRAMID = PyramidConfig()  # soulctl's default: 40 sub-apertures, oversampling 2, 3 lambda/D


def optical_system(frame_rate_hz: float, modes: int):
    """Telescope, source, mirror, pyramid, KL basis and the modal reconstructor (noise-free
    push-pull calibration around a flat wavefront)."""
    tel = Telescope(
        resolution=PYRAMID.pupil.n_pixels,
        diameter=LBT_DIAMETER_M,
        samplingTime=1 / frame_rate_hz,
        centralObstruction=LBT_OBSTRUCTION,
        display_optical_path=False,
        fov=10,
    )
    ngs = Source(optBand="I2", magnitude=0)
    assert abs(ngs.wavelength - WFS_WAVELENGTH_M) < 1e-12, "OOPAO's I2 band is soulctl's 750 nm"
    ngs * tel
    dm = DeformableMirror(telescope=tel, nSubap=SUBAPERTURES_BIN1, mechCoupling=0.35, print_dm_properties=False)
    wfs = Pyramid(
        nSubap=SUBAPERTURES_BIN1,
        telescope=tel,
        modulation=PYRAMID.modulation_lambda_over_d,
        lightRatio=0.5,
        n_pix_separation=4,
        psfCentering=False,
        postProcessing="slopesMaps_incidence_flux",
    )
    m2c = compute_KL_basis(tel, atmosphere(tel, 1.0, 1), dm, lim=1e-3)[:, :modes]
    ngs**tel
    calib = InteractionMatrix(ngs=ngs, tel=tel, dm=dm, wfs=wfs, M2C=m2c, stroke=1e-9, nMeasurements=20, noise="off", print_time=False)
    modes_in_pupil = dm.modes[tel.pupil.ravel() > 0] @ m2c
    return tel, ngs, dm, wfs, m2c, m2c @ calib.M, np.linalg.pinv(modes_in_pupil)


def atmosphere(tel, seeing: float, seed: int):
    """soulctl's LBT profile (heights, Cn2 weights, speeds, directions) at this seeing."""
    cfg = AtmosphereConfig.lbt_default(seeing_arcsec=seeing)
    layers = cfg.layers
    atm = Atmosphere(
        telescope=tel,
        r0=cfg.r0_m,
        L0=cfg.L0_m,
        windSpeed=[la.wind_speed_m_s for la in layers],
        fractionalR0=list(cfg.weights),
        windDirection=[la.wind_direction_deg for la in layers],
        altitude=[la.altitude_m for la in layers],
    )
    atm.initializeAtmosphere(tel)
    if seed != 1:
        atm.generateNewPhaseScreen(seed=seed)
    return atm


def hold(system, seeing: float, gain: float, frames: int, linear: int, delay_frames: float, seed: int) -> dict:
    """Linear sensor for ``linear`` frames, then the pyramid; residual RMS per span."""
    tel, ngs, dm, wfs, m2c, reconstructor, projector = system
    atm = atmosphere(tel, seeing, seed)
    n, e = fractional_taps(delay_frames)
    history = [np.zeros(reconstructor.shape[0])] * (n + 1)  # c(k), c(k - 1), ... newest first
    dm.coefs = 0
    rms = np.zeros(frames)
    start = time.time()
    for k in range(frames):
        atm.update()
        ngs**atm * tel * dm * wfs
        opd = tel.OPD[tel.pupil > 0]
        rms[k] = np.std(opd) * 1e9
        measured = m2c @ (projector @ (opd - opd.mean())) if k < linear else reconstructor @ wfs.signal
        history = [history[0] - gain * measured] + history[:-1]
        dm.coefs = (1 - e) * history[n - 1] + e * history[n]  # during frame k + 1
    described = {"simulator": "OOPAO 1.0.0", "seeing": seeing, "integrator_gain": gain, "delay_frames": delay_frames, "seed": seed}
    return described | {"linear_frames": linear, "frames": frames, "seconds": round(time.time() - start, 1), "spans": spans(rms, linear)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeings", default="1.0,1.2,1.4,1.6")
    p.add_argument("--gain", type=float, default=0.25, help="every mode's integrator gain")
    p.add_argument("--frames", type=int, default=2550, help="1.5 s at 1700 Hz, as pyramid_hold.py")
    p.add_argument("--linear", type=int, default=510, help="frames on the linear sensor (0.3 s)")
    p.add_argument("--seed", type=int, default=1, help="OOPAO's phase-screen seed (1: its built-in screens)")
    p.add_argument("--out", type=Path, default=OUT)
    a = p.parse_args()
    r97 = observation_for_magnitude(9.7)
    system = optical_system(r97.frame_rate_hz, r97.modes)
    rows = []
    for seeing in (float(s) for s in a.seeings.split(",")):
        row = hold(system, seeing, a.gain, a.frames, a.linear, r97.delay_frames, a.seed) | provenance()
        print(json.dumps(row), flush=True)
        rows.append(row)
    atomic_write_text(a.out, json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
