"""Telemetry: the one data model of a loop's records (``schema``), what the simulated loop
keeps while it runs (``recorder``) and the formats it is written to and read from (``hdf5``)."""
