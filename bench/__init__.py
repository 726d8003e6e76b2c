"""Benchmarks: each a module run as ``python -m bench.<name>`` from the repository's root
(docs/development.md); every result they write carries ``results_file.provenance``."""
