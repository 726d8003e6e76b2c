"""Detected photons on the pyramid WFS from the guide star's R magnitude."""

from __future__ import annotations

import math
from dataclasses import dataclass

from .. import tables
from ..errors import InputError
from .pupil import LBT_DIAMETER_M


@dataclass(frozen=True)
class WfsPhotometry:
    """Zero point of the WFS: detected photons per second in one binning-1 sub-aperture at R = 0
    (throughput and quantum efficiency included).  A sub-aperture at binning b collects b^2 times
    as much."""

    zero_point_ph_s: float
    reference_subapertures: int = 40
    pupil_diameter_m: float = LBT_DIAMETER_M
    source: str = ""

    def __post_init__(self):
        if not (self.zero_point_ph_s > 0 and math.isfinite(self.zero_point_ph_s)):
            raise InputError(f"zero point must be a positive number of photons per second, got {self.zero_point_ph_s}")

    @classmethod
    def from_table(cls) -> WfsPhotometry:
        t = tables.photometry_terms()
        return cls(
            zero_point_ph_s=float(t["zero_point_ph_s_per_subaperture"]),
            reference_subapertures=int(t["reference_subapertures"]),
            pupil_diameter_m=float(t["pupil_diameter_m"]),
            source=str(t.get("source", "")),
        )

    @property
    def zero_point_ph_s_m2(self) -> float:
        """The same zero point per square metre of pupil."""
        side = self.pupil_diameter_m / self.reference_subapertures
        return self.zero_point_ph_s / side**2

    def photons_per_second(self, magnitude_r: float, binning: int) -> float:
        """Detected photons per second in one sub-aperture."""
        return self.zero_point_ph_s * 10.0 ** (-0.4 * magnitude_r) * binning**2

    def photons_per_frame(self, magnitude_r: float, binning: int, frame_rate_hz: float) -> float:
        """Detected photons per sub-aperture per frame (all four pupil images together)."""
        return self.photons_per_second(magnitude_r, binning) / frame_rate_hz

    def magnitude(self, photons_per_frame: float, binning: int, frame_rate_hz: float) -> float:
        """The R magnitude that gives this many photons per sub-aperture per frame."""
        return -2.5 * math.log10(photons_per_frame * frame_rate_hz / (self.zero_point_ph_s * binning**2))
