"""The LBT pupil as seen by SOUL: a disc of 8.222 m with a central obstruction of 0.111 (linear).

Both figures are the pupil conjugated to the adaptive secondary (LBTO elab_lib
``ao_global_data_init.pro``; arte ``astro/telescopes.py``).  The secondary's support spiders
are not seen by the WFS (they sit in front of the ASM) and are not modelled.

Sampling convention (used by every optical model): an ``n``-pixel grid whose pixel centres sit
at ``(i + 0.5 - n/2) * pixel_scale`` from the pupil centre, x along columns, y along rows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ..errors import InputError

LBT_DIAMETER_M = 8.222
LBT_OBSTRUCTION = 0.111
MAS_PER_RAD = 180.0 / math.pi * 3600e3


def grid(n: int, pixel_scale_m: float) -> tuple[np.ndarray, np.ndarray]:
    """x (columns) and y (rows) in metres at the pixel centres of an n x n grid."""
    c = (np.arange(n) + 0.5 - n / 2) * pixel_scale_m
    return np.meshgrid(c, c)


@dataclass(frozen=True)
class Pupil:
    n_pixels: int
    diameter_m: float = LBT_DIAMETER_M
    obstruction: float = LBT_OBSTRUCTION

    def __post_init__(self):
        if not (8 <= self.n_pixels <= 4096):
            raise InputError(f"pupil sampling must be 8..4096 pixels across, got {self.n_pixels}")
        if not (self.diameter_m > 0):
            raise InputError(f"pupil diameter must be > 0 m, got {self.diameter_m}")
        if not (0 <= self.obstruction < 1):
            raise InputError(f"central obstruction must be in [0, 1), got {self.obstruction}")

    @property
    def pixel_scale_m(self) -> float:
        return self.diameter_m / self.n_pixels

    @cached_property
    def mask(self) -> np.ndarray:
        """Boolean n x n mask: pixel centres inside the annulus."""
        x, y = grid(self.n_pixels, self.pixel_scale_m)
        r = np.hypot(x, y)
        radius = self.diameter_m / 2
        return (r <= radius) & (r >= self.obstruction * radius)

    @property
    def n_valid(self) -> int:
        return int(self.mask.sum())

    def coordinates(self) -> tuple[np.ndarray, np.ndarray]:
        """x, y (m) of the pixels inside the pupil, in the order of ``mask`` (row-major)."""
        x, y = grid(self.n_pixels, self.pixel_scale_m)
        return x[self.mask], y[self.mask]

    def nm_per_mas_tilt(self) -> float:
        """nm RMS of the unit-RMS Tip ramp (``tilt``) per mas of wavefront tilt: RMS(x) x 1 mas
        in rad x 1e9."""
        x, _ = self.coordinates()
        return float(np.sqrt(np.mean((x - x.mean()) ** 2))) * 1e9 / MAS_PER_RAD

    def tilt(self) -> tuple[np.ndarray, np.ndarray]:
        """Tip (x) and Tilt (y) ramps on the pupil pixels, zero mean and unit RMS."""
        out = []
        for c in self.coordinates():
            c = c - c.mean()
            out.append(c / np.sqrt(np.mean(c**2)))
        return out[0], out[1]


class PupilResampler:
    """OPD maps on ``source``'s grid onto ``target``'s, a finer sampling of the same pupil: the
    pupil's values carried outwards to the nearest pupil pixel (so that interpolation does not
    pull the rim towards zero), then cubic spline interpolation on pixel areas.  What SPECULA's
    pyramid does to its electric field to reach its field of view; here for the pyramid's
    sensing pupil (``pwfs.PyramidConfig.field_of_view_arcsec``)."""

    def __init__(self, source: Pupil, target: Pupil):
        if target.n_pixels < source.n_pixels or (source.diameter_m, source.obstruction) != (target.diameter_m, target.obstruction):
            raise InputError(f"resampling goes to a finer grid of the same pupil, got {source} -> {target}")
        from scipy import ndimage  # here, not at the top: the CLI starts without scipy.ndimage

        _, (self._rows, self._cols) = ndimage.distance_transform_edt(~source.mask, return_indices=True)
        self.factor = target.n_pixels / source.n_pixels

    def __call__(self, opd: np.ndarray) -> np.ndarray:
        """(n, n) or (batch, n, n) float32 on the source grid -> the same on the target grid
        (map by map: a spline along the batch axis would cost 9x one map's)."""
        filled = np.asarray(opd, dtype=np.float64)[..., self._rows, self._cols]
        if filled.ndim == 2:
            return self._zoom(filled)
        maps = [self._zoom(m) for m in filled.reshape(-1, *filled.shape[-2:])]
        return np.stack(maps).reshape(*filled.shape[:-2], *maps[0].shape)

    def _zoom(self, filled: np.ndarray) -> np.ndarray:
        from scipy import ndimage

        return ndimage.zoom(filled, self.factor, order=3, grid_mode=True, mode="nearest").astype(np.float32)
