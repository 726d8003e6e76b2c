"""soulctl: configure, simulate, analyse and tune the control of a pyramid-WFS SCAO system
such as SOUL at the Large Binocular Telescope (Agapito et al. 2021)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("soulctl")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0+unknown"
