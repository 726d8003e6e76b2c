"""Optical models: atmosphere, LBT pupil, adaptive secondary and modal basis, modulated pyramid
WFS with detector, calibration and optical gains, photometry (docs/physics.md)."""
