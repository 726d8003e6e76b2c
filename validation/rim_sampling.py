"""Is the rim's false lock a property of the pyramid or of the simulation's sampling?  One grid
point's own run (``edge_runaway.run_path``'s live phases), the residual OPD taken at given
times, each read offline by two noiseless pyramids with the table's modulation:

* ``loop``: the loop's own sensor, the pupil on 80 pixels (oversampling 2): its focal plane
  is +-40 lambda/D at 750 nm, so a phase step of more than half a wave between two pixels
  comes back with the other sign (the pupil's Nyquist), and light beyond 40 lambda/D wraps
  into the field;
* ``fine``: the same OPD interpolated (``optics.pupil.PupilResampler``) on 160 pixels
  (oversampling 4), the focal plane +-80 lambda/D, and a field stop at the WFS's field of view
  (2.1", radius FIELD_STOP of 55.8 lambda/D at 750 nm on 8.222 m; docs field notes): what a
  sensor of the real field reads of a continuous phase;
* ``fine_open``, ``fine_stop40``: the same without a stop, with one at 40 lambda/D;
* ``three``: the package's own wide field (``PyramidConfig.field_of_view_arcsec`` = 2.1: the
  OPD interpolated on 120 pixels, +-60 lambda/D, the same stop).

Both are read through the loop's reconstructor at k = 1, as measured modes.  Per snapshot: the
residual's modal content ``true`` (the mirror's projection), and each sensor's gain on it, in
the interaction matrix's weakest directions and over all modes: <m, true> / <true, true>.  A
small copy of each snapshot (x SMALL) read by both checks that the two sensors agree where
both are linear.  If ``loop`` reads the runaway's weak directions at ~0 and ``fine`` does
not, the false lock is the simulation's sampling; if both read ~0, the pyramid's own.

Found at R11.9 1.5" seed 3 (mgm+ogtl; docs/physics.md, "Over the magnitudes").  ~6 min per
point on one core, plus ~1 min per snapshot for the fine sensor.

Run:  python -m validation.rim_sampling --seed 3 --times 11.6,12.4,13.2,14.0,16.0,20.0 [--out FILE]
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from soulctl.defaults import SOUL_FIELD_OF_VIEW_ARCSEC
from soulctl.files import atomic_write_text
from soulctl.optics.pupil import PupilResampler
from soulctl.optics.pwfs import Pyramid, PyramidConfig
from soulctl.optics.sensor import WavefrontSensor
from validation.edge_runaway import live_phases, weak_directions  # noqa: E402
from validation.optimize_magnitudes import point_arguments, point_loops
from validation.provenance import provenance

FIELD_STOP = PyramidConfig(field_of_view_arcsec=SOUL_FIELD_OF_VIEW_ARCSEC).stop_lambda_over_d  # the 2.1" field's radius, lambda/D
SMALL = 0.02  # the linear copy's scale
# The sensors reading each snapshot: name -> (oversampling, field stop radius in lambda/D; 0
# none), or the package's wide field ("fov").  ``loop`` is the loop's own; the others see the
# OPD interpolated on their finer pupil.
SENSORS = {"loop": (2, 0.0), "fine": (4, FIELD_STOP), "fine_open": (4, 0.0), "fine_stop40": (4, 39.9), "three": "fov"}


class Taken(Exception):
    """Every snapshot is taken: the run stops there."""


class Snapshots:
    """Keeps the OPD the loop's pyramid receives at the given frames (wraps ``intensity`` on
    that one instance)."""

    def __init__(self, loop, frames: dict[int, float]):
        self.loop, self.frames, self.opd = loop, frames, {}
        self._intensity = loop.sensor.pyramid.intensity
        loop.sensor.pyramid.intensity = self.read

    def read(self, opd: np.ndarray) -> np.ndarray:
        if self.loop.frame in self.frames:
            self.opd[self.frames[self.loop.frame]] = np.array(opd, dtype=np.float32)
            if len(self.opd) == len(self.frames):
                raise Taken
        return self._intensity(opd)


def capture(point, times_s: list[float]) -> tuple[dict[float, np.ndarray], dict | None]:
    """The residual OPD (80 x 80, nm) at ``times_s`` of the point's live phases; where it diverged."""
    loop, rate = point.session.loop, point.request.run.observation.frame_rate_hz
    snaps = Snapshots(loop, {round(t * rate): t for t in times_s})
    diverged = None
    try:
        _, diverged = live_phases(point)
    except Taken:
        pass
    finally:
        del loop.sensor.pyramid.intensity  # the instance's wrapper: the class's method again
    return snaps.opd, diverged


def other_sensor(loop, spec) -> tuple[WavefrontSensor, PupilResampler | None]:
    """The loop's pyramid at another oversampling and field stop (``spec``), or with the
    package's wide field; the same detector; the resampling of the loop's OPD it needs."""
    c = loop.sensor.pyramid.config
    if spec == "fov":
        config = replace(c, field_of_view_arcsec=SOUL_FIELD_OF_VIEW_ARCSEC)
    else:
        config = replace(c, oversampling=spec[0], field_stop_lambda_over_d=spec[1])
    sensor = WavefrontSensor(Pyramid(config), loop.sensor.detector, loop.sensor.photons_per_frame)
    return sensor, None if sensor.pupil == loop.pupil else PupilResampler(loop.pupil, sensor.pupil)


def matched(fine: WavefrontSensor, coarse: WavefrontSensor) -> np.ndarray:
    """Indices into the fine sensor's slopes in the order of the coarse sensor's sub-apertures."""
    key = {tuple(p): i for i, p in enumerate(fine.pyramid.subaperture_pixels[:, 3].tolist())}
    order = np.array([key[tuple(p)] for p in coarse.pyramid.subaperture_pixels[:, 3].tolist()])
    n = fine.n_subapertures
    return np.r_[order, order + n]


def gains(measured: np.ndarray, true: np.ndarray, weak: np.ndarray) -> dict:
    """The sensor's gain on the snapshot: over all modes and in the weak directions."""
    w_m, w_t = weak @ measured, weak @ true
    return {"all": float(measured @ true / (true @ true)), "weak": float(w_m @ w_t / (w_t @ w_t))}


def read(point, snapshots: dict[float, np.ndarray]) -> list[dict]:
    """Each snapshot read by each of SENSORS, at full scale and x SMALL (``_small``)."""
    loop = point.session.loop
    R = np.asarray(point.cal.reconstructor, dtype=np.float64)
    weak, _ = weak_directions(point.cal.interaction_matrix)
    sensors = {name: (loop.sensor, None) if name == "loop" else other_sensor(loop, spec) for name, spec in SENSORS.items()}
    orders = {name: matched(sensor, loop.sensor) for name, (sensor, _) in sensors.items()}
    mask = loop.pupil.mask
    rows = []
    for t, opd in sorted(snapshots.items()):
        true = loop.project(opd[mask])
        row = {"t_s": t, "residual_nm": float(np.sqrt(np.mean(opd[mask] ** 2))), "true_weak_nm": float(np.linalg.norm(weak @ true))}
        for name, (sensor, resample) in sensors.items():
            seen = opd if resample is None else resample(opd)
            for scale, tag in ((1.0, ""), (SMALL, "_small")):
                m = R @ sensor.slopes(scale * seen).astype(np.float64)[orders[name]] / scale
                row[name + tag] = gains(m, true, weak)
        print(line(row), flush=True)
        rows.append(row)
    return rows


def line(row: dict) -> str:
    return f"{row['t_s']:5.1f} s  residual {row['residual_nm']:5.0f} nm  weak {row['true_weak_nm']:5.0f} nm  gain all/weak: " + "  ".join(
        f"{name} {row[name]['all']:+.3f}/{row[name]['weak']:+.3f} ({row[name + '_small']['weak']:.2f})" for name in SENSORS
    )


def main() -> None:
    p = point_arguments(__doc__, wfs_field=0.0)  # the loop's pyramid against SOUL's field: the sampled one
    p.add_argument("--times", default="11.6,12.4,13.2,14.0,16.0,20.0", help="seconds, comma-separated")
    p.add_argument("--snapshots", type=Path, default=None, help="the snapshots (.npz): read from it if it exists, else written to it")
    a = p.parse_args()
    point = point_loops(a.mag, a.seeing, a.seed, a.variant, wfs_field=a.wfs_field)
    diverged: dict | str | None = "not known: the snapshots were read from a file"
    if a.snapshots and a.snapshots.exists():
        with np.load(a.snapshots) as f:
            snapshots = {float(t): f[t] for t in f.files}
    else:
        snapshots, diverged = capture(point, [float(t) for t in a.times.split(",")])
        if a.snapshots:
            np.savez_compressed(a.snapshots, **{f"{t:g}": v for t, v in snapshots.items()})
    print(f"diverged {diverged}; field stop {FIELD_STOP:.1f} lambda/D", flush=True)
    out = {"mag": a.mag, "seeing": a.seeing, "seed": a.seed, "variant": a.variant, **provenance()}
    out |= {"field_stop_lambda_over_d": FIELD_STOP, "sensors": SENSORS, "diverged": diverged, "snapshots": read(point, snapshots)}
    if a.out:
        atomic_write_text(a.out, json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
