"""Grids of `loop run` cases on Dask (`soulctl sweep`)."""
