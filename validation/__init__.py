"""Validation studies: long runs against the paper's operating points, each a module run as
``python -m validation.<study>`` from the repository's root (docs/development.md); their shared
provenance in ``provenance``."""
