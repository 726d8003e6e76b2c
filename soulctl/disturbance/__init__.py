"""Disturbance models as temporal power spectral densities: turbulent Tip/Tilt and telescope vibrations."""
