"""A grid point's `optimize gains` row with a pyramid whose simulated field covers the WFS's
field of view: every loop of the optimisation (``evaluation._new_loop``) reads its residual OPD,
interpolated on a finer pupil (``optics.pupil.PupilResampler``), through a pyramid at oversampling
``--oversampling`` with the 2.1" field stop (``rim_sampling.FIELD_STOP``), instead of the table's
pupil of 80 pixels whose focal plane is +-40 lambda/D (0.75") with no stop.  The calibration,
the screens, the noise draws and everything else are the grid's: the interaction matrix and
reconstructor are the table's, since both sensors read a small OPD the same within 1-2 %
(``rim_sampling.py``, its x0.02 copies).

Why: at R11.9 1.5" seed 3 the grid's loop ran into a false lock of the pupil's rim, and
``rim_sampling.py`` found the loop's pyramid reading the runaway with a gain of ~0 or below
while one of the real field reads it at +0.013 to +0.035, and a healthy residual ~40 % lower
(0.15 against 0.25): at 1.5" the seeing halo at 750 nm is wider than the simulated field, and
what falls outside it wraps back onto the opposite faces (docs/physics.md, "Over the
magnitudes").  ~3x the grid's time per row (the fine pyramid's FFTs are 384 points against 192).

Run:  python -m validation.field_of_view --mag 11.9 --seeing 1.5 --seed 3 [--variant mgm+ogtl] [--oversampling 4] [--out FILE]
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np

import soulctl.loop.evaluation as evaluation_module
import soulctl.loop.optimize as optimize_module
from soulctl.cli.common import default_cache_dir
from soulctl.files import atomic_write_text
from soulctl.optics.pupil import PupilResampler
from soulctl.optics.pwfs import Pyramid
from soulctl.optics.sensor import WavefrontSensor
from validation.optimize_magnitudes import point_arguments, run_case
from validation.provenance import provenance
from validation.rim_sampling import FIELD_STOP  # noqa: E402


class WideField:
    """A pyramid with the loop's detector geometry that reads the loop's OPD (on ``coarse``'s
    pupil) interpolated on its own finer pupil: at ``oversampling`` with a field stop of
    ``stop`` lambda/D.  Duck-types the ``Pyramid`` members a ``WavefrontSensor`` and the loop use."""

    def __init__(self, coarse: Pyramid, oversampling: int, stop: float):
        self.fine = Pyramid(replace(coarse.config, oversampling=oversampling, field_stop_lambda_over_d=stop))
        self.config, self.pupil = self.fine.config, coarse.pupil
        self.upsample = PupilResampler(coarse.pupil, self.fine.pupil)
        if self.config.frame_shape != coarse.config.frame_shape:
            raise ValueError(f"the wide-field pyramid's frame {self.config.frame_shape} is not the loop's {coarse.config.frame_shape}")
        self.subaperture_pixels = coarse.subaperture_pixels  # the RTC's valid sub-apertures, as calibrated

    def intensity(self, opd: np.ndarray) -> np.ndarray:
        return self.fine.intensity(self.upsample(opd))

    @property
    def reference_intensity(self) -> np.ndarray:
        return self.fine.reference_intensity


def widen(oversampling: int, stop: float) -> None:
    """Every loop ``optimize`` makes from now on reads through a ``WideField`` pyramid (its
    session's, ``optimize``, and its evaluations', ``evaluation``)."""
    new_loop = evaluation_module._new_loop

    def wide_loop(*args, **kwargs):
        loop = new_loop(*args, **kwargs)
        s = loop.sensor
        loop.sensor = WavefrontSensor(WideField(s.pyramid, oversampling, stop), s.detector, s.photons_per_frame)
        return loop

    optimize_module._new_loop = evaluation_module._new_loop = wide_loop


def main() -> None:
    p = point_arguments(__doc__, wfs_field=0.0)  # the loops' pyramid widened from the sampled one
    p.add_argument("--oversampling", type=int, default=4)
    a = p.parse_args()
    widen(a.oversampling, FIELD_STOP)
    row = run_case(a.mag, a.seeing, a.seed, a.variant, str(default_cache_dir()), wfs_field=a.wfs_field)
    sensor = {"oversampling": a.oversampling, "field_stop_lambda_over_d": FIELD_STOP}
    row |= {**provenance(), "sensor": sensor}
    w = row.get("windows") or {}
    print(f"diverged at {row['diverged_at']}; before {w.get('mean_before')} after {w.get('mean_after')} +- {w.get('standard_error')}")
    print(f"settled k {row.get('settled_k')}; restores {row['safety_restores']}; {row['seconds']:.0f} s")
    if a.out:
        atomic_write_text(a.out, json.dumps(row, indent=1))


if __name__ == "__main__":
    main()
