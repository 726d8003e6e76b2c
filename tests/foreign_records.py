"""Closed-loop records of another AO system whose plant is known exactly, written as AOT FITS
with aotpy alone (not soulctl's writer): a Tip/Tilt loop of a quad-cell-like sensor
(m = chi (phi - mirror) + n), any controller given by its time filter (num, den in powers of
z^-1), the mirror holding the commands delayed by d frames (the fractional part as linear
interpolation between frames, soulctl's delay line), white measurement noise, low-pass
turbulence and one vibration line.  The truth each test compares with is in ``TRUTH``."""

from __future__ import annotations

import aotpy
import numpy as np
from scipy.signal import lfilter

RATE = 1000.0
TRUTH = {"delay": 2.5, "chi": 1.0}
# an integrator with a first-order low-pass: g / (1 - z^-1) x (1 - a) / (1 - a z^-1), a = 0.5
LOW_PASS = (np.array([0.5]), np.array([1.0, -1.5, 0.5]))


def modal_loop(frames: int, gains, num=LOW_PASS[0], den=LOW_PASS[1], delay=TRUTH["delay"], chi=TRUTH["chi"], seed=1, noise=1.0):
    """(measurements m, commands c), (frames, modes), of the loop c = gains (num / den) m, one
    mode per gain: Tip and Tilt (the first two) with a 20 Hz line (2.5 mas RMS on a 10 m pupil), each mode's turbulence
    falling with its order."""
    gains = np.atleast_1d(np.asarray(gains, dtype=float))
    rng = np.random.default_rng(seed)
    drive = rng.standard_normal((frames, len(gains))) * 0.02 / np.sqrt(np.arange(1, len(gains) + 1))
    phi = lfilter([1.0], np.poly([0.995, 0.99]), drive, axis=0)  # turbulence-like: flat below ~1 Hz, f^-4 above
    t = np.arange(frames) / RATE
    line = 30.0 * np.stack([np.sin(2 * np.pi * 20.0 * t), np.cos(2 * np.pi * 20.0 * t + 0.3)], axis=1)
    phi[:, : min(2, len(gains))] += line[:, : min(2, len(gains))]
    n_int, e = int(delay), delay - int(delay)
    b, a = np.asarray(num, dtype=float), np.asarray(den, dtype=float)
    m, c = np.zeros_like(phi), np.zeros_like(phi)
    noise_series = rng.standard_normal(phi.shape) * noise
    for k in range(frames):
        mirror = (1 - e) * (c[k - n_int] if k >= n_int else 0.0) + e * (c[k - n_int - 1] if k >= n_int + 1 else 0.0)
        m[k] = chi * (phi[k] - mirror) + noise_series[k]
        past_m = sum(b[i] * m[k - i] for i in range(len(b)) if k >= i)
        past_c = sum(a[j] * c[k - j] for j in range(1, len(a)) if k >= j)
        c[k] = (gains * past_m - past_c) / a[0]
    return m, c


def tip_tilt_loop(frames: int, gain: float, num=LOW_PASS[0], den=LOW_PASS[1], delay=TRUTH["delay"], chi=TRUTH["chi"], seed=1, noise=1.0):
    """(measurements m, commands c) (frames, 2) of the Tip/Tilt loop c = gain (num / den) m."""
    return modal_loop(frames, [gain, gain], num, den, delay, chi, seed, noise)


def write_aot(path, m, c, gain: float, num=LOW_PASS[0], den=LOW_PASS[1], delay=None, telescope="a 10 m telescope"):
    """The loop as AOT FITS: a one-sub-aperture Shack-Hartmann (a quad cell) measuring the
    modes in nm, a tip-tilt mirror, the time filter gain x num / den, the delay if given."""
    star = aotpy.NaturalGuideStar("NGS")
    time = aotpy.Time("LOOP TIME", frame_numbers=list(range(len(m))))
    n = m.shape[1]
    wfs = aotpy.ShackHartmann(
        "QUAD CELL", source=star, n_valid_subapertures=1, measurements=aotpy.Image("M", np.asarray(m, np.float32)[:, :, None], "nm", time)
    )  # (frames, modes, 1): the quad cell's x and y as the modes
    system = aotpy.AOSystem(ao_mode="SCAO", name="a simulated Tip/Tilt loop")
    system.main_telescope = aotpy.MainTelescope(telescope, enclosing_diameter=10.0)
    mirror = aotpy.TipTiltMirror("TTM", telescope=system.main_telescope)
    loop = aotpy.ControlLoop("TT LOOP", input_sensor=wfs, commanded_corrector=mirror, time=time, framerate=RATE, delay=delay)
    loop.modal_coefficients = aotpy.Image("C", np.asarray(c, np.float32), "nm", time)
    loop.measurements_to_modes = aotpy.Image("R", np.eye(n, dtype=np.float32)[:, :, None])
    loop.time_filter_num = aotpy.Image("NUM", np.tile(gain * np.asarray(num, dtype=float), (n, 1)))
    loop.time_filter_den = aotpy.Image("DEN", np.tile(np.asarray(den, dtype=float), (n, 1)))
    system.sources, system.wavefront_sensors, system.wavefront_correctors, system.loops = [star], [wfs], [mirror], [loop]
    system.write_to_file(str(path), overwrite=True)
    return path
