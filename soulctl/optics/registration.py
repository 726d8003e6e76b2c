"""Mis-registration between the pyramid and the adaptive secondary.

The interaction matrix is calibrated with the mirror where the pyramid saw it then; in the loop
the mirror's actuators, as projected on the pyramid's pupil, may have moved: shifted, rotated
about the pupil's centre, or magnified (the pupil re-imaged at another scale).  The loop then
applies the mirror's influence functions at

    p' = m R(theta) p + s,   each function's width scaled by m,

while the reconstructor stays the calibration's.  Units as AO engineers quote them: the shift
in actuator pitches (the LBT672's mean pitch, ``AsmGeometry.pitch_m``), the rotation in
degrees, the magnification as a ratio.  Heritage: OOPAO's ``misRegistration`` (shiftX/Y,
rotationAngle, radialScaling) and the mis-registration studies of the LBT and VLT ASMs
(Heritier et al. 2018).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..ranges import MAGNIFICATION, ROTATION_DEG, SHIFT_PITCH


@dataclass(frozen=True, kw_only=True)
class Misregistration:
    shift_x_pitch: float = 0.0
    shift_y_pitch: float = 0.0
    rotation_deg: float = 0.0
    magnification: float = 1.0

    def __post_init__(self):
        SHIFT_PITCH.check(self.shift_x_pitch, "misregistration.shift_x_pitch")
        SHIFT_PITCH.check(self.shift_y_pitch, "misregistration.shift_y_pitch")
        ROTATION_DEG.check(self.rotation_deg, "misregistration.rotation_deg")
        MAGNIFICATION.check(self.magnification, "misregistration.magnification")

    @property
    def is_identity(self) -> bool:
        return self == Misregistration()

    def positions(self, positions_m: np.ndarray, pitch_m: float) -> np.ndarray:
        """(n, 2) actuator positions (m) as the pyramid sees them: p' = m R(theta) p + s."""
        a = np.deg2rad(self.rotation_deg)
        rotation = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        shift = np.array([self.shift_x_pitch, self.shift_y_pitch]) * pitch_m
        return self.magnification * positions_m @ rotation.T + shift

    def pitch(self, pitch_m: float) -> float:
        """The influence functions' scale length as the pyramid sees it."""
        return self.magnification * pitch_m
