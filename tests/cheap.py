"""Options of the cheapest pyramid, for the suite's tests of paths and contracts: the coarsest
sampling (--oversampling 1) and the field its pupil samples (--wfs-field 0).  SOUL's 2.1" field,
the runs' default, would make every such loop a loop at sensing oversampling 3, ~6x the cost
(docs/performance.md); the default field has tests of its own."""

CHEAP_PYRAMID = ["--oversampling", "1", "--wfs-field", "0"]
